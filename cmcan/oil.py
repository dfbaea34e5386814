"""Hydraulic oil properties: ASTM D341 (Walther) viscosity and a linear density law.

Shared by the simulator and the model's leakage law. Defaults are ISO VG 46 (HLP 46): 46 cSt at 40 C
and 6.8 cSt at 100 C. The Walther constants are derived from the two reference points so that the
law passes through them exactly. A grade name stands for a mineral HLP oil of viscosity index ~100.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

KELVIN = 273.15


@dataclass(frozen=True)
class Oil:
    nu40_cst: float = 46.0
    nu100_cst: float = 6.8
    density15_kg_m3: float = 870.0
    # Thermal expansion lowers density by about 0.065 % per K for mineral oils.
    density_per_k: float = 0.00065

    @property
    def walther_ab(self) -> tuple[float, float]:
        """(A, B) of log10(log10(nu + 0.7)) = A - B * log10(T_K)."""
        y40 = math.log10(math.log10(self.nu40_cst + 0.7))
        y100 = math.log10(math.log10(self.nu100_cst + 0.7))
        x40 = math.log10(40.0 + KELVIN)
        x100 = math.log10(100.0 + KELVIN)
        b = (y40 - y100) / (x100 - x40)
        a = y40 + b * x40
        return a, b

    def kinematic_viscosity_cst(self, temp_c: ArrayLike) -> NDArray[np.float64]:
        a, b = self.walther_ab
        t_k = np.asarray(temp_c, dtype=float) + KELVIN
        return 10.0 ** (10.0 ** (a - b * np.log10(t_k))) - 0.7

    def density_kg_m3(self, temp_c: ArrayLike) -> NDArray[np.float64]:
        return self.density15_kg_m3 * (1.0 - self.density_per_k * (np.asarray(temp_c, dtype=float) - 15.0))

    def dynamic_viscosity_pa_s(self, temp_c: ArrayLike) -> NDArray[np.float64]:
        return self.kinematic_viscosity_cst(temp_c) * 1e-6 * self.density_kg_m3(temp_c)


VG46 = Oil()

# ISO 3448 grades as mineral HLP oils (viscosity index about 100): kinematic viscosity at 40 C and 100 C.
GRADES: dict[str, tuple[float, float]] = {
    "VG15": (15.0, 3.4),
    "VG22": (22.0, 4.3),
    "VG32": (32.0, 5.4),
    "VG46": (46.0, 6.8),
    "VG68": (68.0, 8.7),
    "VG100": (100.0, 11.2),
}


def oil_from_grade(grade: str) -> Oil:
    """An oil by its ISO grade name (``VG46``, ``ISO VG 46``, ``HLP46`` and ``46`` all name VG 46)."""
    key = "VG" + "".join(ch for ch in grade.upper() if ch.isdigit())
    if key not in GRADES:
        raise ValueError(f"unknown oil grade {grade!r}; known: {', '.join(GRADES)} (or give nu40_cst and nu100_cst)")
    nu40, nu100 = GRADES[key]
    return Oil(nu40_cst=nu40, nu100_cst=nu100)
