"""Record all bus traffic of a run to a file, and replay it into a monitor offline.

File format (``.mbr``, "morph bus record"): a stream of msgpack objects. The first is the header
``{"format": "morph-sim-bus-record", "version": 1, "run_id": …, "config": RunConfig JSON, "started_at": …}``; every
other is one received sample ``[receive_time, key, payload, sender, seq, sent_at]`` (``payload`` = the wire bytes,
untouched). The file is appended and flushed at least once a second, so a killed recorder loses at most a second.

Replay feeds the samples, in receive order, to a fresh :class:`MonitorService` that writes a new run record: every
metric of the record can be recomputed without rerunning the simulation.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack

from schemas.keys import RunKeys
from services.bus.base import Sample
from services.runconfig import RunConfig

FORMAT = "morph-sim-bus-record"
VERSION = 1
FLUSH_SECONDS = 1.0
END_GRACE = 0.5  # seconds recorded after the sim's end of run (the last acks and the monitor's final streams)


class BusRecorder:
    """Subscribes to ``morph/<run>/**`` on ``bus`` and appends every sample to ``path``."""

    def __init__(self, bus, config: RunConfig, path: Path):
        self.bus = bus
        self.config = config
        self.keys = RunKeys(config.run_id)
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "ab")
        self._packer = msgpack.Packer(use_bin_type=True)
        if self.path.stat().st_size == 0:
            self._file.write(self._packer.pack({"format": FORMAT, "version": VERSION, "run_id": config.run_id,
                                                "config": config.model_dump(mode="json"), "started_at": time.time()}))
        self._last_flush = time.monotonic()
        self.frames = 0
        self.ticks = 0  # sim ticks recorded (progress)
        self._tick_key = self.keys.tick
        self._end = asyncio.Event()

    def on_sample(self, sample: Sample) -> None:
        self._file.write(self._packer.pack([time.time(), sample.key, bytes(sample.payload), sample.sender,
                                            sample.seq, sample.sent_at]))
        self.frames += 1
        if sample.key == self._tick_key:
            self.ticks += 1
        now = time.monotonic()
        if now - self._last_flush >= FLUSH_SECONDS:
            self._file.flush()
            self._last_flush = now
        rel = self.keys.relative(sample.key)
        if (rel == ["ctl", "stop"] and sample.sender == "sim") or (rel[:1] == ["events"] and b"run.finished" in
                                                                    bytes(sample.payload)):
            self._end.set()

    async def run(self, timeout: float | None = None, subscription=None) -> int:
        """Record until the run ends (plus a short grace) or ``timeout`` seconds; returns the frames written.
        ``subscription``: one already feeding :meth:`on_sample` (closed at the end), else one is declared here."""
        sub = subscription or await self.bus.subscribe(self.keys.everything, self.on_sample)
        try:
            try:
                await asyncio.wait_for(self._end.wait(), timeout)
                await asyncio.sleep(END_GRACE)
            except asyncio.TimeoutError:
                pass
        finally:
            await sub.close()
            self.close()
        return self.frames

    def stop(self) -> None:
        self._end.set()

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._file.close()


def read_record(path: Path) -> tuple[dict[str, Any], Iterator[Sample]]:
    """The header and an iterator over the samples of a bus record (a truncated last frame is ignored)."""
    f = open(path, "rb")
    unpacker = msgpack.Unpacker(f, raw=False, strict_map_key=False)
    try:
        header = next(unpacker)
    except StopIteration:
        f.close()
        raise ValueError(f"record: {path} is empty") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        f.close()
        raise ValueError(f"record: {path} is not a morph-sim bus record")
    if header.get("version") != VERSION:
        f.close()
        raise ValueError(f"record: version {header.get('version')} is not supported (this build reads {VERSION})")

    def samples() -> Iterator[Sample]:
        try:
            for frame in unpacker:
                _, key, payload, sender, seq, sent_at = frame
                yield Sample(key, payload, sender, seq, sent_at)
        except (msgpack.OutOfData, ValueError):
            return  # a frame cut by a killed recorder
        finally:
            f.close()

    return header, samples()


async def replay(path: Path, output_dir: Path, run_id: str | None = None):
    """Feed a bus record into a fresh monitor writing ``output_dir/<run_id>``; returns its MonitorResult."""
    from services.bus.local import LocalNetwork
    from services.monitor.service import MonitorService

    header, samples = read_record(Path(path))
    values = dict(header["config"])
    values.update(output_dir=str(output_dir), endpoint=None, listen=None)
    if run_id is not None:
        values["run_id"] = run_id
    config = RunConfig.coerce(values)
    if (config.record_dir / "metrics.csv").exists():
        raise ValueError(f"output_dir: {config.record_dir} already holds a run record; replay into another directory")
    original = RunKeys(header["run_id"])
    bus = LocalNetwork().session("replay")
    monitor = MonitorService(config, bus, max_rate=0.0)
    try:
        for s in samples:
            if monitor.done:
                break
            if config.run_id != header["run_id"]:
                s = s._replace(key=monitor.keys._k(*original.relative(s.key)))
            monitor.on_sample(s)
        monitor.finish()
        await asyncio.sleep(0)  # let the probes' answers (published into the void) finish
    finally:
        await bus.close()
    return monitor.result
