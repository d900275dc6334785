# syntax=docker/dockerfile:1
# morph-sim: one image for every service of a run (sim, agent, monitor) and for `morph-sim up`.
#
#   docker build -t morph-sim:0.1.0 .
#   docker run --rm --init -v morph-runs:/data/runs morph-sim:0.1.0                 # the default: a tiny local run
#   docker compose up --build                                                         # the distributed graph
#
# Two stages: the first turns the source tree into a wheel (its build backend stays in that stage), the second
# installs only that wheel and its runtime dependencies (all of them ship manylinux wheels: no compiler, no apt).
# tests/test_dockerfile.py checks these steps and replays them outside Docker (wheel -> fresh venv -> morph-sim up).

ARG PYTHON_IMAGE=python:3.11-slim

FROM ${PYTHON_IMAGE} AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY schemas ./schemas
COPY services ./services
COPY morph_sim ./morph_sim
RUN python -m pip wheel --no-deps --wheel-dir /wheels .

FROM ${PYTHON_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_ROOT_USER_ACTION=ignore \
    MORPH_OUTPUT_DIR=/data/runs
# A fixed non-root uid so a bind-mounted runs directory can be chown'ed to it (docs/deploy.md).
RUN groupadd --system --gid 10001 morph \
 && useradd --system --uid 10001 --gid morph --create-home --home-dir /home/morph --shell /usr/sbin/nologin morph \
 && mkdir -p /data/runs \
 && chown morph:morph /data/runs
COPY --from=build /wheels /tmp/wheels
# Install the wheel with its base dependencies only (numpy, scipy, msgpack, pydantic, prometheus-client and the
# pinned eclipse-zenoh==1.10.2): what the sim, an agent and the monitor need. The tool's extras (plots, reports,
# terminal views, benchmarks) stay out of the image; `morph-sim up` without them prints its final line only. Then
# drop the installers: the runtime image needs neither pip nor setuptools.
RUN python -m pip install /tmp/wheels/*.whl \
 && rm -rf /tmp/wheels \
 && python -m pip uninstall --yes setuptools wheel pip
# Numeric: Kubernetes checks runAsNonRoot against the image's user, which it cannot do for a name.
USER 10001:10001
WORKDIR /home/morph
# Run records (MORPH_OUTPUT_DIR). A named volume mounted here starts out owned by the morph user.
VOLUME ["/data/runs"]
# 7447: the Zenoh endpoint the sim hosts; 9464: the monitor's Prometheus exporter (--prometheus-port).
EXPOSE 7447/tcp 9464/tcp
# Services stop on SIGTERM (compose's stop signal) within their grace period.
STOPSIGNAL SIGTERM
CMD ["morph-sim", "up", "--scale", "tiny", "--quiet"]
