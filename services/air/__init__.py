"""The shared air: the radio of a run whose network profile limits rates, as a service of its own."""
