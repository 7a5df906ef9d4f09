"""tools/export_lerobot.py: export recordings, load them with LeRobot, compare
every frame with the MCAP source.

Runs in the LeRobot venv:

    "$(tools/lerobot-venv)" -m pytest tests/lerobot/test_export_lerobot.py

Source: OFFWORLD_EPISODES_DIR when set (real recordings), else samples written
by tests/lerobot/make_sample_episodes.py. The expected values are computed here from
the MCAP files with their own small reader (make_reader + DecoderFactory),
not with the exporter's code.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

os.environ["HF_HUB_OFFLINE"] = "1"  # before lerobot / huggingface_hub are imported

import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

HERE = Path(__file__).resolve().parent
EXPORT = HERE.parent.parent / "tools" / "export_lerobot.py"
REPO_ID = "offworld/test"
USING_SAMPLES = not os.environ.get("OFFWORLD_EPISODES_DIR")


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def run_export(*args, check=True) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, str(EXPORT), *map(str, args)],
                       capture_output=True, text=True, timeout=1800)
    if check and p.returncode != 0:
        raise AssertionError(f"export failed ({p.returncode}):\n{p.stderr}")
    return p


# ------------------------------------------------------------- reference reader

def _ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _rows(img, bpp):
    buf = np.frombuffer(bytes(img.data), dtype=np.uint8)
    return buf[: img.height * img.step].reshape(img.height, img.step)[:, : img.width * bpp]


def ref_color(img) -> np.ndarray:
    assert img.encoding in ("rgb8", "bgr8"), img.encoding
    a = _rows(img, 3).reshape(img.height, img.width, 3)
    return a[:, :, ::-1] if img.encoding == "bgr8" else a


def ref_depth(img) -> np.ndarray:
    end = ">" if img.is_bigendian else "<"
    if img.encoding == "32FC1":
        d = np.ascontiguousarray(_rows(img, 4)).view(end + "f4").astype(np.float32)
        return np.where(np.isfinite(d), d, np.float32(0)).astype(np.float32)
    assert img.encoding in ("16UC1", "mono16"), img.encoding
    mm = np.ascontiguousarray(_rows(img, 2)).view(end + "u2")
    return mm.astype(np.float32) / np.float32(1000)


def read_source(path: Path, pixels: bool = False) -> dict:
    """EpisodeInfo, the Steps with their color/depth/pose (file order), odometry, counts.
    Without `pixels` the images keep only header, encoding and size (real recordings
    are large: only one episode's pixels are held at a time)."""
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        header = r.get_header()
        metadata = {m.name: dict(m.metadata) for m in r.iter_metadata()}
        summary = r.get_summary()
        channels = {c.topic: (c.message_encoding, summary.schemas[c.schema_id])
                    for c in summary.channels.values()}
        topics_in_order, info, end, steps, odom, cur = [], None, None, [], [], {}
        log_not_stamp = []  # topics whose log_time is not the header stamp (capture time)
        for _, ch, msg, ros in r.iter_decoded_messages(log_time_order=False):
            t = ch.topic
            topics_in_order.append((t, msg.log_time))
            if t in ("/camera/color/image_raw", "/camera/depth/image_raw", "/tracker/pose",
                     "/odom") and msg.log_time != _ns(ros.header):
                log_not_stamp.append(t)
            if t == "/offworld/episode":
                info = ros
            elif t == "/offworld/episode_end":
                end = ros
            elif t == "/odom":
                odom.append((_ns(ros.header), len(odom), ros))
            elif t in ("/camera/color/image_raw", "/camera/depth/image_raw", "/tracker/pose"):
                assert t not in cur, f"{path}: two {t} in step {len(steps)}"
                if t != "/tracker/pose" and not pixels:
                    ros = SimpleNamespace(header=ros.header, encoding=ros.encoding,
                                          height=ros.height, width=ros.width)
                cur[t] = (ros, msg.log_time)
            elif t == "/offworld/step":
                steps.append((ros, msg.log_time, cur))
                cur = {}
    return {"path": path, "profile": header.profile, "metadata": metadata, "channels": channels,
            "order": topics_in_order, "log_not_stamp": log_not_stamp, "info": info, "end": end, "steps": steps, "odom": odom}


def expected_frames(src: dict) -> list[dict]:
    steps, odom = src["steps"], src["odom"]
    out = []
    for i in range(len(steps) - 1):
        s, _, obs = steps[i]
        nxt = steps[i + 1][0]
        t = _ns(s.header)
        before = [(to, j, o) for to, j, o in odom if to <= t]
        if before:
            o = max(before, key=lambda e: (e[0], e[1]))[2]
            op, ot = o.pose.pose, o.twist.twist
            od = [op.position.x, op.position.y, _yaw(op.orientation), ot.linear.x, ot.angular.z]
        else:
            od = [0.0] * 5
        p = obs["/tracker/pose"][0].pose
        cont = list(nxt.action_continuous)
        out.append({
            "color": ref_color(obs["/camera/color/image_raw"][0]),
            "depth": ref_depth(obs["/camera/depth/image_raw"][0]),
            "state": np.array([p.position.x, p.position.y, _yaw(p.orientation), *od],
                              dtype=np.float64).astype(np.float32),
            "capture_time_ns": t,
            "capture_time_s": s.header.stamp.sec + s.header.stamp.nanosec / 1e9,
            "action": np.array([nxt.linear_x, nxt.angular_z], dtype=np.float32),
            "action.discrete": nxt.action_discrete,
            "action.normalized": np.array(cont if cont else [0.0, 0.0], dtype=np.float32),
            "reward": np.float32(nxt.reward),
            "done": bool(nxt.terminated or nxt.truncated),
            "truncated": bool(nxt.truncated),
            "success": bool(nxt.success),
            "task": src["info"].task or src["info"].env_id,
        })
    return out


# ------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def episodes_dir(tmp_path_factory) -> Path:
    if not USING_SAMPLES:
        d = Path(os.environ["OFFWORLD_EPISODES_DIR"])
        assert d.is_dir(), f"OFFWORLD_EPISODES_DIR={d} is not a directory"
        return d
    d = tmp_path_factory.mktemp("recordings") / "runs"
    _load("make_sample_episodes").make_samples(d)
    return d


@pytest.fixture(scope="module")
def sources(episodes_dir) -> list[dict]:
    """The exportable episodes, in the dataset's order."""
    srcs = [read_source(p) for p in sorted(episodes_dir.rglob("*.mcap"))]
    srcs = [s for s in srcs if len(s["steps"]) >= 2]
    srcs.sort(key=lambda s: (s["info"].env_id, s["info"].experiment_id, s["info"].episode_id,
                             str(s["path"])))
    assert srcs, f"no episode with a step under {episodes_dir}"
    return srcs


@pytest.fixture(scope="module")
def exported(episodes_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "ds"
    proc = run_export(episodes_dir, out, "--repo-id", REPO_ID)
    return out, proc.stderr


@pytest.fixture(scope="module")
def dataset(exported):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(REPO_ID, root=exported[0])


# ------------------------------------------------------------- tests

def test_sources_follow_the_documented_format(sources):
    """What the exporter relies on from docs/recording.md."""
    for s in sources:
        name = s["path"].name
        assert s["profile"] == "ros2", name
        for topic, (enc, schema) in s["channels"].items():
            assert enc == "cdr" and schema.encoding == "ros2msg", (name, topic)
        assert s["order"][0][0] == "/offworld/episode", name
        if s["end"] is not None:
            assert s["order"][-1][0] == "/offworld/episode_end", name
            if not s["end"].end_reason.startswith("recorder_stopped"):
                assert s["end"].steps == len(s["steps"]) - 1, name
        assert not s["log_not_stamp"], (name, "log_time != stamp", sorted(set(s["log_not_stamp"])))
        meta = s["metadata"].get("offworld.episode")
        assert meta is not None, f"{name}: no offworld.episode metadata record"
        for key in ("env_id", "task", "experiment_id", "episode_id"):
            assert meta.get(key) == str(getattr(s["info"], key)), (name, key, meta.get(key))
        stamps = []
        for k, (step, log_time, obs) in enumerate(s["steps"]):
            assert step.step == k and step.episode_id == s["info"].episode_id, (name, k)
            t = _ns(step.header)
            for topic in ("/camera/color/image_raw", "/camera/depth/image_raw"):
                img, img_log = obs[topic]
                assert _ns(img.header) == t == img_log, (name, k, topic, "stamp != step stamp")
            assert "/tracker/pose" in obs, (name, k)
            if k == 0:
                assert step.action_discrete == -1 and len(step.action_continuous) == 0, name
            stamps.append(t)
        assert stamps == sorted(stamps), f"{name}: step stamps go back"
        n_cmd = sum(1 for topic, _ in s["order"] if topic == "/cmd_vel")
        assert n_cmd == len(s["steps"]) - 1, (name, "one /cmd_vel per step but the reset", n_cmd)


def test_episodes_and_lengths(dataset, sources, exported):
    assert dataset.num_episodes == len(sources)
    assert dataset.num_frames == sum(len(s["steps"]) - 1 for s in sources)
    eps = dataset.meta.episodes
    start = 0
    for e, s in enumerate(sources):
        n = len(s["steps"]) - 1
        assert eps[e]["episode_index"] == e
        assert eps[e]["length"] == n, s["path"]
        assert (eps[e]["dataset_from_index"], eps[e]["dataset_to_index"]) == (start, start + n)
        assert eps[e]["tasks"] == [s["info"].task or s["info"].env_id]
        start += n
    # the sidecar names each episode's source
    rows = [json.loads(line) for line in
            (exported[0] / "meta" / "offworld_episodes.jsonl").read_text().splitlines()]
    assert [r["episode_index"] for r in rows] == list(range(len(sources)))
    assert [r["episode_id"] for r in rows] == [s["info"].episode_id for s in sources]
    assert [r["env_id"] for r in rows] == [s["info"].env_id for s in sources]


def test_fps_is_the_median_step_rate(dataset, sources):
    stamps = [[_ns(st[0].header) for st in s["steps"]] for s in sources]
    periods = [b - a for ts in stamps for a, b in zip(ts, ts[1:])]
    want = max(1, round(1e9 / statistics.median([p for p in periods if p > 0])))
    assert dataset.fps == want
    assert dataset.meta.info["fps"] == want
    if USING_SAMPLES:
        assert want == 4


def test_every_frame_equals_the_source(dataset, sources, exported):
    # float64 capture times: exact in the parquet files (LeRobotDataset gives float32)
    table = pq.ParquetDataset(sorted((exported[0] / "data").rglob("*.parquet"))).read(
        columns=["index", "observation.capture_time_s"]).to_pydict()
    capture_s = dict(zip(table["index"], table["observation.capture_time_s"]))

    index = 0
    for e, s in enumerate(sources):
        frames = expected_frames(read_source(s["path"], pixels=True))
        for i, want in enumerate(frames):
            got = dataset[index]
            where = f"{s['path'].name} frame {i}"
            assert int(got["episode_index"]) == e and int(got["frame_index"]) == i, where
            assert int(got["index"]) == index, where
            img = got["observation.images.color"]
            assert img.dtype == torch.float32 and tuple(img.shape) == (3, *want["color"].shape[:2])
            rgb = (img * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
            np.testing.assert_array_equal(rgb, want["color"], err_msg=where + " color")
            depth = got["observation.depth"].numpy()
            assert depth.dtype == np.float32, where
            np.testing.assert_array_equal(depth, want["depth"], err_msg=where + " depth")
            np.testing.assert_array_equal(got["observation.state"].numpy(), want["state"],
                                          err_msg=where + " state")
            assert int(got["observation.capture_time_ns"]) == want["capture_time_ns"], where
            assert capture_s[index] == want["capture_time_s"], where
            np.testing.assert_array_equal(got["action"].numpy(), want["action"], err_msg=where)
            assert int(got["action.discrete"]) == want["action.discrete"], where
            np.testing.assert_array_equal(got["action.normalized"].numpy(), want["action.normalized"],
                                          err_msg=where)
            assert np.float32(got["next.reward"].item()) == want["reward"], where
            assert bool(got["next.done"]) is want["done"], where
            assert bool(got["next.truncated"]) is want["truncated"], where
            assert bool(got["next.success"]) is want["success"], where
            assert got["task"] == want["task"], where
            assert float(got["timestamp"]) == pytest.approx(i / dataset.fps, abs=1e-6), where
            index += 1
        # the episode's last frame carries how it ended
        last = s["steps"][-1][0]
        assert bool(dataset[index - 1]["next.done"]) is bool(last.terminated or last.truncated)
    assert index == len(dataset)


def test_skipped_files_are_reported(episodes_dir, exported):
    err = exported[1]
    for p in episodes_dir.rglob("*.mcap.partial"):
        assert f"skip {p.relative_to(episodes_dir)}" in err
    if USING_SAMPLES:
        # the samples hold a .partial and an episode that is only its reset
        assert "ep-000004.mcap.partial" in err
        assert "ep-000003.mcap: no step after the reset" in err
        assert "done: 3 episodes, 12 frames, fps 4" in err
        # the samples cover both depth encodings, both action kinds, NaN depth and no-odometry
        srcs = [read_source(p) for p in episodes_dir.rglob("*.mcap")]
        encs = {st[2]["/camera/depth/image_raw"][0].encoding for s in srcs for st in s["steps"]}
        assert encs == {"32FC1", "16UC1"}


def test_usage_errors_exit_2(tmp_path, episodes_dir):
    p = run_export(tmp_path / "nope", tmp_path / "out", "--repo-id", REPO_ID, check=False)
    assert p.returncode == 2 and "no such directory" in p.stderr
    (tmp_path / "out").mkdir()
    p = run_export(episodes_dir, tmp_path / "out", "--repo-id", REPO_ID, check=False)
    assert p.returncode == 2 and "exists" in p.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "ep-000001.mcap.partial").write_bytes(b"\x89MCAP0\r\n")
    p = run_export(empty, tmp_path / "out2", "--repo-id", REPO_ID, check=False)
    assert p.returncode == 2 and "no episode to export" in p.stderr, p.stderr
    assert "ep-000001.mcap.partial" in p.stderr
    assert not (tmp_path / "out2").exists()
    if USING_SAMPLES:  # 8 px wide: SVT-AV1 would crash (SIGFPE), refused up front
        p = run_export(episodes_dir, tmp_path / "out3", "--repo-id", REPO_ID, "--videos", check=False)
        assert p.returncode == 2 and "--vcodec h264" in p.stderr, p.stderr
        assert not (tmp_path / "out3").exists()


def test_bad_file_fails_before_writing_or_is_skipped(tmp_path, sources):
    src = tmp_path / "src"
    src.mkdir()
    first, last = sources[0], sources[-1]
    # names that sort against the episodes' order: the export orders by EpisodeInfo
    shutil.copy(last["path"], src / "a.mcap")
    shutil.copy(first["path"], src / "b.mcap")
    data = first["path"].read_bytes()
    (src / "c.mcap").write_bytes(data[: len(data) // 2])  # cut, yet named complete
    p = run_export(src, tmp_path / "out", "--repo-id", REPO_ID, check=False)
    assert p.returncode == 1, p.stderr
    assert "c.mcap" in p.stderr and "nothing written" in p.stderr
    assert not (tmp_path / "out").exists()
    assert not list(tmp_path.glob("out.partial-*"))

    p = run_export(src, tmp_path / "out", "--repo-id", REPO_ID, "--skip-bad", "--fps", "7")
    assert "skip c.mcap" in p.stderr
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=tmp_path / "out")
    assert ds.fps == 7
    want = [first] if first is last else [first, last]
    assert ds.num_episodes == len(want)
    assert list(ds.meta.episodes["length"]) == [len(s["steps"]) - 1 for s in want]
    rows = [json.loads(line) for line in
            (tmp_path / "out" / "meta" / "offworld_episodes.jsonl").read_text().splitlines()]
    assert [r["source"] for r in rows] == ["b.mcap", "a.mcap"][: len(want)]
    start = 0
    for s in want:
        assert int(ds[start]["observation.capture_time_ns"]) == _ns(s["steps"][0][0].header)
        start += len(s["steps"]) - 1


def test_videos_smoke(tmp_path, episodes_dir, sources):
    """--videos: color as an h264 video (lossy); everything else exact."""
    out = tmp_path / "vds"
    run_export(episodes_dir, out, "--repo-id", REPO_ID, "--videos", "--vcodec", "h264")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    # torchcodec (lerobot's default decoder) needs FFmpeg's shared libraries on the system
    ds = LeRobotDataset(REPO_ID, root=out, video_backend="pyav")
    assert ds.meta.info["features"]["observation.images.color"]["dtype"] == "video"
    assert ds.num_episodes == len(sources)
    assert list(ds.meta.episodes["length"]) == [len(s["steps"]) - 1 for s in sources]
    want = expected_frames(read_source(sources[-1]["path"], pixels=True))
    last = ds[len(ds) - 1]
    h, w = want[-1]["color"].shape[:2]
    assert tuple(last["observation.images.color"].shape) == (3, h, w)
    np.testing.assert_array_equal(last["observation.depth"].numpy(), want[-1]["depth"])
    np.testing.assert_array_equal(last["observation.state"].numpy(), want[-1]["state"])
