"""Units: the library computes in centimetres and reports in millimetres.

Datasets are converted to cm when they are imported (:data:`UNITS_TO_CM`); every length a user reads (errors,
residuals, noise, tolerances) is in mm, converted here and nowhere else.
"""

from __future__ import annotations

from lgi.errors import InputError

#: Millimetres per centimetre: multiply a library length (cm) by it to report mm.
MM_PER_CM = 10.0

#: Centimetres per unit of the lengths a user's files may hold.
UNITS_TO_CM = {"mm": 0.1, "cm": 1.0, "m": 100.0, "in": 2.54}


def check_units(units: str, what: str = "units") -> float:
    """The factor to cm of ``units``, or an :class:`InputError` naming ``what``."""
    if units not in UNITS_TO_CM:
        raise InputError(f"{what}: unknown units {units!r}; use one of {sorted(UNITS_TO_CM)}")
    return UNITS_TO_CM[units]
