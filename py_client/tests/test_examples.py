"""The shipped examples run (the ones that need no extra packages)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run(script: str, *args: str, stdin: str | None = None) -> str:
    out = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_random_agent_runs_episodes():
    out = run("random_agent.py", "--episodes", "1", "--seed", "3")
    assert "episode 0: return" in out
    assert "steps/s" in out


def test_teleop_follows_scripted_keys():
    out = run("teleop.py", stdin="wwad\nq\n")
    lines = [line for line in out.splitlines() if line.startswith(("w:", "a:", "d:"))]
    assert [line[0] for line in lines] == ["w", "w", "a", "d"]
    assert "step 4" in lines[-1]


def test_teleop_records_human_demonstrations(tmp_path):
    from mcap.reader import make_reader

    run("teleop.py", "--record", str(tmp_path), "--experiment", "demos", stdin="wwr\nd\nq\n")
    files = sorted(tmp_path.rglob("*.mcap"))
    assert [f.name for f in files] == ["ep-000000.mcap", "ep-000001.mcap"]
    for f, steps in zip(files, (2, 1)):
        with open(f, "rb") as fh:
            reader = make_reader(fh)
            meta = {m.name: m.metadata for m in reader.iter_metadata()}["offworld.episode"]
            assert reader.get_summary().statistics.channel_message_counts
            step_channel = next(c.id for c in reader.get_summary().channels.values() if c.topic == "/offworld/step")
            assert reader.get_summary().statistics.channel_message_counts[step_channel] == steps + 1
        assert (meta["learning_type"], meta["experiment"]) == ("humandemos", "demos")


def _progress(out: Path) -> list[dict[str, str]]:
    import csv

    with open(out / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


def _success(rows: list[dict[str, str]]) -> float:
    episodes = sum(int(r["episodes"]) for r in rows)
    return sum(float(r["success_rate"]) * int(r["episodes"]) for r in rows) / episodes


def test_the_vector_env_example_is_deterministic_for_a_seed(tmp_path):
    args = ("--num-envs", "2", "--iterations", "3", "--steps-per-iteration", "100", "--seed", "5")
    first = run("train_vec_reinforce.py", *args, "--out", str(tmp_path / "a"))
    second = run("train_vec_reinforce.py", *args, "--out", str(tmp_path / "b"))
    assert (tmp_path / "a/progress.csv").read_bytes() == (tmp_path / "b/progress.csv").read_bytes()
    assert [line for line in first.splitlines() if line.startswith("iteration")] == [
        line for line in second.splitlines() if line.startswith("iteration")
    ]
    rows = _progress(tmp_path / "a")
    # Two envs, 100 vector steps an iteration.
    assert [(r["iteration"], r["steps"]) for r in rows] == [("0", "200"), ("1", "400"), ("2", "600")]
    assert all(int(r["episodes"]) > 0 for r in rows), rows


def test_the_vector_env_example_learns_to_reach_the_monolith(tmp_path):
    """REINFORCE over make_vec with next-step autoreset: 40 iterations (seed 0)
    take the success rate from ~48 % (the first 10) to ~78 % (the last 10)."""
    import numpy as np

    run("train_vec_reinforce.py", "--iterations", "40", "--out", str(tmp_path))
    rows = _progress(tmp_path)
    assert len(rows) == 40
    early, late = _success(rows[:10]), _success(rows[-10:])
    assert late > early + 0.25, (early, late)
    weights = np.load(tmp_path / "policy.npz")["weights"]
    assert weights.shape == (4 * 8 + 1, 4)


def test_the_dqn_example_names_its_knobs_and_what_it_needs():
    out = run("train_dqn.py", "--help")
    for flag in ("--env-id", "--seed", "--resolution", "--learning-rate", "--buffer-size", "--exploration-fraction"):
        assert flag in out, out
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        missing = subprocess.run(
            [sys.executable, str(EXAMPLES / "train_dqn.py"), "--steps", "10"], capture_output=True, text=True, timeout=60
        )
        assert missing.returncode == 2, missing
        assert "pip install stable-baselines3" in missing.stderr, missing.stderr
        assert "Traceback" not in missing.stderr, missing.stderr


def test_learning_curve_png(tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "curve.png"
    run("plot_learning_curve.py", "--episodes", "2", "--out", str(png))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
