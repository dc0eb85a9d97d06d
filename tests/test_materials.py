import numpy as np
import pytest

from sonicverse_core.errors import MaterialError
from sonicverse_core.scene.mapping import MAPPINGS, CategoryMapping, load_mapping
from sonicverse_core.scene.materials import BANDS, MATERIAL_NAMES, MATERIALS, get_material, mass_law_tl


def test_24_materials_with_reference_absorption():
    assert len(MATERIALS) == 24
    # spot values from Resonance Audio's room_effects_utils.cc
    assert get_material("AcousticCeilingTiles").absorption[5] == 0.920
    assert get_material("CurtainHeavy").absorption == (0.073, 0.106, 0.140, 0.350, 0.550, 0.720, 0.700, 0.650, 1.0)
    assert get_material("Marble").absorption[-1] == 0.040
    assert get_material("Transparent").absorption == (1.0,) * 9
    for m in MATERIALS.values():
        a = np.array(m.absorption)
        assert a.shape == (9,) and np.all((a >= 0) & (a <= 1))
        assert 0 <= m.scattering <= 1


def test_transmission_loss_follows_mass_law():
    # 4 mm glass (10 kg/m^2) measures 26-30 dB at 500 Hz; heavy block walls ~50 dB
    assert 24 <= get_material("GlassThin").transmission_loss_db[4] <= 31
    assert 45 <= get_material("ConcreteBlockPainted").transmission_loss_db[4] <= 55
    assert get_material("Transparent").transmission_loss_db == (0.0,) * 9
    for m in MATERIALS.values():
        tl = np.array(m.transmission_loss_db)
        assert np.all(np.diff(tl) >= 0), m.name  # mass law rises with frequency
        assert np.all((tl >= 0) & (tl <= 60))
    tl = mass_law_tl(10.0)
    np.testing.assert_allclose(np.diff(tl[3:6]), 20 * np.log10(2), atol=1e-9)  # +6 dB per octave
    assert len(BANDS) == 9


def test_unknown_material_suggests_names():
    with pytest.raises(MaterialError, match="Marble"):
        get_material("Marbel")


def test_mappings_and_user_override(tmp_path):
    assert MAPPINGS["igibson"].material_for("walls") == "ConcreteBlockPainted"
    assert MAPPINGS["igibson"].material_for("floors") == "WoodPanel"
    assert MAPPINGS["igibson"].material_for("window") == "GlassThick"
    assert MAPPINGS["mp3d"].material_for("ceiling") == "AcousticCeilingTiles"
    assert MAPPINGS["mp3d"].material_for("fireplace") == "BrickBare"
    assert MAPPINGS["mp3d"].material_for("shower_floor") == "PolishedConcreteOrTile"
    assert MAPPINGS["mp3d"].material_for("spaceship") == "Uniform"
    f = tmp_path / "m.json"
    f.write_text('{"sofa": "Grass", "__default__": "Marble"}')
    m = load_mapping(f)
    assert m.material_for("sofa") == "Grass" and m.material_for("anything") == "Marble"
    f.write_text('{"sofa": "Gras"}')
    with pytest.raises(MaterialError):
        load_mapping(f)
    with pytest.raises(MaterialError):
        CategoryMapping({"x": "Nope"})
    assert set(MATERIAL_NAMES) == set(MATERIALS)
