"""JTORATC (Sun et al. 2024, "Multi-objective optimization for multi-UAV-assisted mobile edge computing"),
re-implemented on this project's service model: a weighted sum of delay, energy and load imbalance minimized per
slot by block-coordinate descent over association, bandwidth (KKT) and trajectory (SCA). docs/PROTOCOL.md §5.

* :mod:`.model`: the objective and the association and bandwidth blocks, the rate's concave surrogate.
* :mod:`.sca`: the trajectory block's convex program (cvxpy).
* :mod:`.controller`: the per-slot BCD, the degradation rule and the controller.
"""
from dswm.methods.jtoratc.controller import JTORATCController, JTORATCSettings

__all__ = ["JTORATCController", "JTORATCSettings"]
