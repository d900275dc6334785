"""Runtime fault control: the ``ctl/faults`` controller every process mounts and the timed schedule file."""
