"""Acoustic materials: 9-band energy absorption, scattering and transmission loss.

Bands (Hz): 31.25, 62.5, 125, 250, 500, 1k, 2k, 4k, 8k (:data:`BANDS`), the octave bands of Resonance Audio's room
model. Absorption coefficients are the 24 materials of Resonance Audio
(resonance-audio/resonance-audio, resonance_audio/platforms/common/room_effects_utils.cc; same numbers in the Web
SDK's src/utils.js).

Transmission loss (dB per band, for sound passing *through* a surface: walls, doors, glass) follows the
field-incidence mass law ``TL(f) = 20 log10(m_s f) - 47`` (L. Long, "Architectural Acoustics", 2nd ed., 2014,
sec. 9.3; also Bies & Hansen, "Engineering Noise Control", eq. 7.43), from a typical surface density ``m_s`` (kg/m^2)
of the construction each material stands for, clipped to [0, 60] dB (above ~60 dB flanking paths dominate in
buildings). It reproduces e.g. 4 mm float glass (10 kg/m^2: 27 dB at 500 Hz, measured 26-30 dB) and a 150 mm
hollow concrete-block wall (150 kg/m^2: 50 dB at 500 Hz, STC 45-50).

Scattering (broadband, 0..1) uses the typical random-incidence values of M. Vorlaender, "Auralization" (2008),
sec. 11.4 and Cox & D'Antonio, "Acoustic Absorbers and Diffusers" (2009): smooth hard surfaces ~0.05, plaster and
panels ~0.1, brick and block 0.2-0.3, folded curtains 0.5, grass 0.6.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from sonicverse_core.errors import MaterialError

#: Centre frequencies of the nine octave bands (Hz).
BANDS = np.array([31.25, 62.5, 125.0, 250.0, 500.0, 1000.0, 2000.0, 4000.0, 8000.0])
BANDS.setflags(write=False)

# name: (9 absorption coefficients, surface density kg/m^2 for the mass law, scattering)
_TABLE = {
    "Transparent": ((1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0), 0.0, 0.0),
    "AcousticCeilingTiles": ((0.672, 0.675, 0.700, 0.660, 0.720, 0.920, 0.880, 0.750, 1.0), 4.5, 0.2),
    "BrickBare": ((0.030, 0.030, 0.030, 0.030, 0.030, 0.040, 0.050, 0.070, 0.140), 220.0, 0.3),
    "BrickPainted": ((0.006, 0.007, 0.010, 0.010, 0.020, 0.020, 0.020, 0.030, 0.060), 220.0, 0.2),
    "ConcreteBlockCoarse": ((0.360, 0.360, 0.360, 0.440, 0.310, 0.290, 0.390, 0.250, 0.500), 140.0, 0.3),
    "ConcreteBlockPainted": ((0.092, 0.090, 0.100, 0.050, 0.060, 0.070, 0.090, 0.080, 0.160), 150.0, 0.2),
    "CurtainHeavy": ((0.073, 0.106, 0.140, 0.350, 0.550, 0.720, 0.700, 0.650, 1.0), 0.5, 0.5),
    "FiberGlassInsulation": ((0.193, 0.220, 0.220, 0.820, 0.990, 0.990, 0.990, 0.990, 1.0), 2.0, 0.3),
    "GlassThin": ((0.180, 0.169, 0.180, 0.060, 0.040, 0.030, 0.020, 0.020, 0.040), 10.0, 0.05),
    "GlassThick": ((0.350, 0.350, 0.350, 0.250, 0.180, 0.120, 0.070, 0.040, 0.080), 25.0, 0.05),
    "Grass": ((0.050, 0.050, 0.150, 0.250, 0.400, 0.550, 0.600, 0.600, 0.600), 1000.0, 0.6),
    "LinoleumOnConcrete": ((0.020, 0.020, 0.020, 0.030, 0.030, 0.030, 0.030, 0.020, 0.040), 350.0, 0.05),
    "Marble": ((0.010, 0.010, 0.010, 0.010, 0.010, 0.010, 0.020, 0.020, 0.040), 300.0, 0.05),
    "Metal": ((0.030, 0.035, 0.040, 0.040, 0.050, 0.050, 0.050, 0.070, 0.090), 12.0, 0.1),
    "ParquetOnConcrete": ((0.028, 0.030, 0.040, 0.040, 0.070, 0.060, 0.060, 0.070, 0.140), 350.0, 0.1),
    "PlasterRough": ((0.017, 0.018, 0.020, 0.030, 0.040, 0.050, 0.040, 0.030, 0.060), 200.0, 0.2),
    "PlasterSmooth": ((0.011, 0.012, 0.013, 0.015, 0.020, 0.030, 0.040, 0.050, 0.100), 200.0, 0.05),
    "PlywoodPanel": ((0.400, 0.340, 0.280, 0.220, 0.170, 0.090, 0.100, 0.110, 0.220), 7.0, 0.1),
    "PolishedConcreteOrTile": ((0.008, 0.008, 0.010, 0.010, 0.015, 0.020, 0.020, 0.020, 0.040), 300.0, 0.05),
    "Sheetrock": ((0.290, 0.279, 0.290, 0.100, 0.050, 0.040, 0.070, 0.090, 0.180), 10.0, 0.1),
    "WaterOrIceSurface": ((0.006, 0.006, 0.008, 0.008, 0.013, 0.015, 0.020, 0.025, 0.050), 1000.0, 0.05),
    "WoodCeiling": ((0.150, 0.147, 0.150, 0.110, 0.100, 0.070, 0.060, 0.070, 0.140), 12.0, 0.1),
    "WoodPanel": ((0.280, 0.280, 0.280, 0.220, 0.170, 0.090, 0.100, 0.110, 0.220), 8.0, 0.1),
    "Uniform": ((0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5), 100.0, 0.5),
}

TL_MAX_DB = 60.0


def mass_law_tl(surface_density: float, bands: np.ndarray = BANDS) -> np.ndarray:
    """Field-incidence mass-law transmission loss (dB) per band, clipped to [0, TL_MAX_DB]."""
    if surface_density <= 0:
        return np.zeros(len(bands))
    return np.clip(20.0 * np.log10(surface_density * bands) - 47.0, 0.0, TL_MAX_DB)


@dataclass(frozen=True)
class Material:
    """An acoustic material.

    absorption : (9,) float, energy absorption per band, in [0, 1]
    scattering : float in [0, 1], fraction of reflected energy scattered diffusely
    transmission_loss_db : (9,) float, dB lost by sound passing through the surface
    """

    name: str
    absorption: tuple
    scattering: float
    transmission_loss_db: tuple

    @property
    def transmission(self) -> np.ndarray:
        """(9,) energy transmission coefficient through the surface."""
        return 10.0 ** (-np.asarray(self.transmission_loss_db) / 10.0)

    def to_json(self) -> dict:
        return {"name": self.name, "absorption": list(self.absorption), "scattering": self.scattering,
                "transmission_loss_db": list(self.transmission_loss_db)}


def _build() -> dict:
    out = {}
    for name, (alpha, density, scat) in _TABLE.items():
        tl = tuple(float(round(v, 2)) for v in mass_law_tl(density))
        out[name] = Material(name, tuple(float(a) for a in alpha), float(scat), tl)
    return out


#: All materials by name (read-only).
MATERIALS = MappingProxyType(_build())
#: Material names in a fixed order; a material's index in this tuple is its id in per-face arrays.
MATERIAL_NAMES = tuple(MATERIALS)
MATERIAL_INDEX = MappingProxyType({n: i for i, n in enumerate(MATERIAL_NAMES)})


def get_material(name: str) -> Material:
    """The material called ``name``; raises :class:`MaterialError` with the closest names if unknown."""
    try:
        return MATERIALS[name]
    except KeyError:
        close = difflib.get_close_matches(name, MATERIAL_NAMES, n=3, cutoff=0.5)
        hint = f" (did you mean {', '.join(close)}?)" if close else f"; known: {', '.join(MATERIAL_NAMES)}"
        raise MaterialError(f"unknown acoustic material '{name}'{hint}") from None


def material_arrays() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(absorption (M, 9), scattering (M,), transmission (M, 9)) indexed by material id."""
    a = np.array([MATERIALS[n].absorption for n in MATERIAL_NAMES])
    s = np.array([MATERIALS[n].scattering for n in MATERIAL_NAMES])
    t = np.array([MATERIALS[n].transmission for n in MATERIAL_NAMES])
    return a, s, t
