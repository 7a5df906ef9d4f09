"""``twin_profile=``: embedded sim twins built from a twin profile file
(``docs/twin-profile.md``) behave like that robot; a bad file is refused
with ``BadRequest`` naming the file and the field."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium
import pytest

import offworld_gym  # noqa: F401  (registers the ids)
from offworld_gym import errors

ENV_ID = "OffWorldMonolithDiscreteSim-v0"
#: The discrete table's "forward" action (0.1 m/s for 0.6 s).
FORWARD = 2


def _forward_distance(**kwargs) -> float:
    """Planar distance covered by three seeded forward steps."""
    env = gymnasium.make(ENV_ID, resolution=(24, 32), **kwargs)
    try:
        _, info = env.reset(seed=3)
        start = info["pose"]
        pose = start
        for _ in range(3):
            _, _, terminated, truncated, info = env.step(FORWARD)
            pose = info["pose"]
            assert not (terminated or truncated)
        return math.hypot(pose[0] - start[0], pose[1] - start[1])
    finally:
        env.close()


def test_a_profile_changes_how_far_the_twin_drives(tmp_path: Path):
    slipping = tmp_path / "slipping.toml"
    slipping.write_text("format = 1\n[motion]\nlinear_gain = 0.5\n")
    nominal = _forward_distance()
    # The same seed and actions, half the traction: half the distance.
    profiled = _forward_distance(twin_profile=slipping)
    assert nominal == pytest.approx(0.18, abs=0.01)
    assert profiled == pytest.approx(0.5 * nominal, rel=0.02)
    # The default profile spelled out is the nominal twin exactly.
    default = tmp_path / "default.toml"
    default.write_text("format = 1\n[motion]\nlinear_gain = 1.0\n")
    assert _forward_distance(twin_profile=str(default)) == nominal


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("[motion]\nlinear_gain = 7.0\n", "motion.linear_gain"),
        ("[camera]\nroll_deg = 1.0\n", "camera.roll_deg"),
        ("format = 2\n", "format"),
    ],
)
def test_a_bad_profile_is_a_bad_request_naming_file_and_field(tmp_path: Path, text: str, field: str):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(errors.BadRequest) as info:
        gymnasium.make(ENV_ID, resolution=(24, 32), twin_profile=path)
    assert info.value.code == 400
    assert str(path) in str(info.value) and field in str(info.value)


def test_a_missing_profile_is_a_bad_request(tmp_path: Path):
    missing = tmp_path / "missing.toml"
    with pytest.raises(errors.BadRequest, match="missing.toml"):
        gymnasium.make(ENV_ID, resolution=(24, 32), twin_profile=missing)


def test_a_profile_is_for_embedded_twins_only(tmp_path: Path):
    path = tmp_path / "p.toml"
    path.write_text("format = 1\n")
    with pytest.raises(errors.ConfigurationError, match="sim_twin --profile"):
        gymnasium.make(ENV_ID, connect="tcp/127.0.0.1:9", twin_profile=path)
