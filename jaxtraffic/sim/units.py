"""The units of the paper's indices, as every table, report and progress line prints them (docs/model.md section 10).

The indices integrate over the road (x in m) and the horizon (t in s) with the density in veh/km, the paper's
Table 2 magnitudes: ``J_TTT`` = int int rho dx dt is in veh/km·m·s, i.e. 10⁻³ veh·s (J_TTT / 1000 is the total
travel time in vehicle-seconds: 3.22e7 at the congested equilibrium over 300 s is 32 200 veh·s); ``J_fuel``
weighs it by the fuel rate xi in ml/s per vehicle; ``J_comfort`` by a² + a_t² (a in m/s², a_t in m/s³: the sum
the paper takes, whose two parts have different units).
"""

from __future__ import annotations

__all__ = ["INDEX_UNITS", "labelled"]

INDEX_UNITS = {"J_TTT": "veh/km·m·s", "J_fuel": "ml/s·veh/km·m·s", "J_comfort": "(m²/s⁴ + m²/s⁶)·veh/km·m·s"}


def labelled(index: str) -> str:
    """``index`` (one of ``INDEX_UNITS``) with its unit, as a table's header or a progress line writes it:
    "J_TTT (veh/km·m·s)"; ``KeyError`` for another name."""
    return f"{index} ({INDEX_UNITS[index]})"
