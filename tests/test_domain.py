"""The domain layer: species groups, PAD group settings, object ids and cube geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from vlsforest.domain.cubes import CUBE_CORNERS, CUBE_FACES, cube_triangles, scaled_cubes
from vlsforest.domain.labels import GROUND_ID, SURROUNDING_ID, object_ids
from vlsforest.domain.leaf_angles import LAD_NAMES, check_lad
from vlsforest.domain.species import GROUPS, PAD_GROUPS, SPECIES_GROUPS, species_group, species_key
from vlsforest.errors import ConfigError
from vlsforest.synth.species import SPECIES, TARGET_SPECIES

ROOT = Path(__file__).resolve().parents[1]


def test_study_species_groups():
    # Weiser et al. (2021): beech and hornbeam are broadleaf, spruce is conifer
    assert species_group("fagus_sylvatica") == "broadleaf"
    assert species_group("carpinus_betulus") == "broadleaf"
    assert species_group("picea_abies") == "conifer"
    assert species_group("  Picea abies ") == "conifer"  # Latin name, any case and blanks
    assert species_group("broadleaf") == "broadleaf" and species_group("conifer") == "conifer"
    assert species_key("Fagus sylvatica") == "fagus_sylvatica"


def test_unknown_species_is_an_error_unless_a_default_is_given():
    with pytest.raises(ConfigError, match="unknown species 'tilia_cordata'"):
        species_group("tilia_cordata")
    assert species_group("tilia_cordata", default="other") == "other"
    assert species_group("tilia_cordata", default=None) is None


def test_groups_agree_with_the_tree_generator():
    assert set(SPECIES_GROUPS.values()) == set(GROUPS)
    for key, sp in SPECIES.items():
        assert species_group(key) == sp.group, key
        assert species_group(sp.latin) == sp.group, sp.latin
    for group, members in TARGET_SPECIES.items():
        assert {species_group(k) for k, _ in members} == {group}


def test_pad_groups_are_the_study_values_and_the_workflow_defaults():
    # the study: broadleaf planophile with PADmax 5 m²/m³, conifer erectophile with PADmax 8
    assert {g: dict(v) for g, v in PAD_GROUPS.items()} == {
        "broadleaf": {"lad": "planophile", "pad_max": 5.0}, "conifer": {"lad": "erectophile", "pad_max": 8.0}}
    assert set(PAD_GROUPS) == set(GROUPS)
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    assert config["pad"]["groups"] == {g: dict(v) for g, v in PAD_GROUPS.items()}
    with pytest.raises(TypeError):
        PAD_GROUPS["conifer"]["pad_max"] = 1.0  # read-only: one definition for every caller


def test_leaf_angle_names():
    assert all(check_lad(v["lad"]) == v["lad"] for v in PAD_GROUPS.values())
    assert check_lad(" Erectophile ") == "erectophile" and "spherical" in LAD_NAMES
    with pytest.raises(ConfigError, match="pad.lad: unknown leaf angle distribution 'banana'"):
        check_lad("banana", "pad.lad")


def test_object_ids():
    assert (GROUND_ID, SURROUNDING_ID) == (1, 2)
    assert object_ids(7) == (71, 72)
    ids = [i for t in range(1, 50) for i in object_ids(t)]
    assert len(set(ids)) == len(ids) and not {GROUND_ID, SURROUNDING_ID} & set(ids)
    for bad in (0, -3):
        with pytest.raises(ConfigError):
            object_ids(bad)


def test_cube_triangles_are_closed_and_face_outwards():
    centre = np.array([[1.0, 2.0, 3.0], [-5.0, 0.5, 0.0]])
    half = np.array([0.5, 0.125])
    v, f = cube_triangles(centre, half, first=3)
    assert v.shape == (16, 3) and f.shape == (24, 3)
    assert f.min() == 24 and f.max() == 39  # indices of cubes 3 and 4 of a larger mesh
    f = f - 24
    for c in range(2):
        tri = v[f[12 * c:12 * (c + 1)]]
        np.testing.assert_allclose(tri.min(axis=(0, 1)), centre[c] - half[c])
        np.testing.assert_allclose(tri.max(axis=(0, 1)), centre[c] + half[c])
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        outward = tri.mean(axis=1) - centre[c]
        assert np.all(np.einsum("ij,ij->i", normal, outward) > 0)
        np.testing.assert_allclose(np.linalg.norm(normal, axis=1).sum() / 2, 6 * (2 * half[c]) ** 2)
    assert CUBE_CORNERS.shape == (8, 3) and CUBE_FACES.shape == (12, 3)


def test_scaled_cube_sides():
    # a/2 = a0/2 · (clip(PAD, 0, PADmax) / PADmax)^alpha, by hand for a0 = 0.25, PADmax = 4
    half = scaled_cubes(np.zeros((5, 3)), [1.0, 4.0, 9.0, -1.0, np.nan], 4.0, a0=0.25, alpha=0.5)
    np.testing.assert_allclose(half, [0.0625, 0.125, 0.125, 0.0, 0.0])
    with pytest.raises(ConfigError):
        scaled_cubes(np.zeros((1, 3)), [1.0], 0.0)
