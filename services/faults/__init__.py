"""Runtime fault control (issue 5): the ``ctl/faults`` controller every process mounts and the timed schedule file."""
