"""The scene convention of an export: which axis is up and which unit a coordinate counts, as the target DCC
expects them.

lgi works in centimetres with Y up (the face looking along +Z), as its datasets are. A DCC that reads USD's
``metersPerUnit`` and ``upAxis`` could convert on import, but several ignore one or both (Blender 4.2 ignores
``metersPerUnit``), so the geometry itself is written in the target's convention and the stage metadata says so.
Z up is the right-handed turn of +90 degrees about X that every Y-up to Z-up exchange uses: (x, y, z) becomes
(x, -z, y), so the face looks along -Y, towards a Z-up DCC's front view.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lgi.errors import InputError

UP_AXES = ("Y", "Z")
#: Centimetres per unit.
UNITS = {"cm": 1.0, "m": 100.0}
#: Each DCC's native convention: (up axis, units).
DCC_PRESETS = {"maya": ("Y", "cm"), "houdini": ("Y", "m"), "blender": ("Z", "m"), "unreal": ("Z", "cm")}



def convention_option(name: str, what: str, group: str | None = None) -> Any:
    """The options ``dcc``, ``up_axis`` and ``units`` of a job writing ``what`` (:func:`lgi.options.option`),
    declared here once for every job that writes in a DCC's convention."""
    from lgi.options import option

    presets = "; ".join(f"{k}: {u} up, {m}" for k, (u, m) in DCC_PRESETS.items())
    helps = {
        "dcc": (tuple(DCC_PRESETS), f"the convention of {what} for a DCC ({presets}); --up-axis and --units given "
                "beside it take precedence. In Blender's, a USD file NAME.usd* comes with NAME.blender.py, the "
                "script that imports it with its frame rate and correctives"),
        "up_axis": (UP_AXES, f"the up axis of {what} (default Y, lgi's; Z turns the face +90 degrees about X: it "
                    "looks along -Y)"),
        "units": (tuple(UNITS), f"the unit of {what}'s coordinates (default cm, lgi's)"),
    }
    choices, text = helps[name]
    return option(None, text, choices=choices, group=group)


_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class Convention:
    """An export's up axis (``"Y"`` or ``"Z"``) and units (``"cm"`` or ``"m"``); the default is lgi's own."""

    up: str = "Y"
    units: str = "cm"

    def __post_init__(self) -> None:
        if self.up not in UP_AXES:
            raise InputError(f"--up-axis takes {' or '.join(UP_AXES)}, not {self.up!r}")
        if self.units not in UNITS:
            raise InputError(f"--units takes {' or '.join(UNITS)}, not {self.units!r}")

    @classmethod
    def of(cls, dcc: str | None = None, up: str | None = None, units: str | None = None) -> Convention:
        """The convention of ``dcc`` (``--dcc``), with ``up`` and ``units`` given explicitly taking precedence;
        lgi's own (Y up, cm) where neither says."""
        if dcc is not None and dcc not in DCC_PRESETS:
            raise InputError(f"--dcc takes one of {', '.join(DCC_PRESETS)}, not {dcc!r}")
        base_up, base_units = DCC_PRESETS[dcc] if dcc else ("Y", "cm")
        return cls(up or base_up, units or base_units)

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) float64: lgi's axes (Y up) to this convention's, a proper rotation."""
        return np.eye(3) if self.up == "Y" else _Z_UP

    @property
    def scale(self) -> float:
        """Units of this convention per centimetre."""
        return 1.0 / UNITS[self.units]

    @property
    def meters_per_unit(self) -> float:
        return UNITS[self.units] / 100.0

    @property
    def native(self) -> bool:
        """True for lgi's own convention (nothing to convert)."""
        return self.up == "Y" and self.units == "cm"

    def points(self, p: np.ndarray, dtype: Any = np.float32) -> np.ndarray:
        """Positions or offsets ``p`` ((..., 3), cm, Y up) in this convention, as ``dtype``."""
        p = np.asarray(p)
        if self.native:
            return p.astype(dtype, copy=False)
        return ((np.asarray(p, np.float64) @ self.rotation.T) * self.scale).astype(dtype)

    def quaternions(self, q: np.ndarray) -> np.ndarray:
        """Rotations ``q`` ((..., 4) float, w first) about lgi's axes, about this convention's (the same angle
        about the turned axis)."""
        q = np.asarray(q, np.float64)
        if self.up == "Y":
            return q
        return np.concatenate([q[..., :1], q[..., 1:] @ self.rotation.T], axis=-1)

    def metadata(self) -> dict[str, str]:
        """What an output's header says of it."""
        return {"units": self.units, "up_axis": self.up}
