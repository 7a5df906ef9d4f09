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


def test_learning_curve_png(tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "curve.png"
    run("plot_learning_curve.py", "--episodes", "2", "--out", str(png))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
