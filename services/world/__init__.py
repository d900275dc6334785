"""The warehouse world: layouts, exact A*, conflict resolution, dynamics, the fleet's base controller and rendering.

Plain code over numpy arrays with no I/O: the sim service (:mod:`services.sim.service`) and the in-process lab drive
it the same way.
"""
