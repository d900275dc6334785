"""Services: bus, sim (warehouse clock), agent, monitor, supervisor and the in-process lab."""
