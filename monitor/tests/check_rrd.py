#!/usr/bin/env python3
"""Verifies an .rrd written by the OffWorld monitor and summarises it as JSON.

Usage: check_rrd.py RECORDING.rrd [--rows]

Runs `rerun rrd verify` (the CLI shipped with rerun-sdk==0.36.3), then reads
the recording back with `rerun.experimental.RrdReader` and prints one JSON
object on stdout:

    {
      "rerun_version": "0.36.3",
      "verify": {"ok": true, "output": "..."},
      "recordings": 1, "blueprints": 2,
      "entities": {
        "/envs/sim/x/robot": {
          "rows": 12,            # temporal rows
          "static_rows": 0,      # static rows (latest wins in the viewer)
          "components": {"Transform3D:translation": 12, ...},  # non-null cells
          "timelines": ["log_time", "sim_time", "step", "wall_time"],
          "step_range": [1, 12]  # min/max of the `step` timeline, if any
        }, ...
      }
    }

With `--rows`, each entity also lists its temporal rows' places on the
timelines, sorted, as `"index": [[step, sim_time_ns, wall_time_ns], ...]`
(`null` where a row is not on that timeline), and the text of its
`TextLog` rows as `"texts": [...]` (in row order).

Exit status: 0 when the summary was printed (the caller judges it), 2 when
rerun-sdk is missing or the file cannot be read at all.
"""

import json
import os
import subprocess
import sys


def main() -> int:
    if len(sys.argv) not in (2, 3) or (len(sys.argv) == 3 and sys.argv[2] != "--rows"):
        print(__doc__, file=sys.stderr)
        return 2
    path = sys.argv[1]
    rows = len(sys.argv) == 3
    try:
        import pyarrow as pa
        import pyarrow.compute as pc
        import rerun as rr
        from rerun.experimental import RrdReader
    except ImportError as e:
        print(f"rerun-sdk==0.36.3 is required (pip install rerun-sdk==0.36.3): {e}", file=sys.stderr)
        return 2

    # The CLI binary ships inside the wheel; `python -m rerun` runs it.
    env = dict(os.environ)
    env.setdefault("CI", "1")  # no first-run analytics banner
    verify = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "verify", path],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )

    try:
        reader = RrdReader(path)
        recordings = reader.recordings()
        blueprints = reader.blueprints()
        chunks = list(reader.stream())
    except Exception as e:  # noqa: BLE001 - report any reader failure
        print(f"cannot read {path}: {e}", file=sys.stderr)
        return 2

    entities: dict = {}
    for chunk in chunks:
        entry = entities.setdefault(
            chunk.entity_path,
            {"rows": 0, "static_rows": 0, "components": {}, "timelines": set(), "step_range": None},
        )
        if rows:
            entry.setdefault("index", [])
            entry.setdefault("texts", [])
        if chunk.is_static:
            entry["static_rows"] += chunk.num_rows
        else:
            entry["rows"] += chunk.num_rows
        timelines = set(chunk.timeline_names)
        entry["timelines"] |= timelines
        batch: pa.RecordBatch = chunk.to_record_batch()
        for name, column in zip(batch.schema.names, batch.columns):
            if name == "rerun.controls.RowId" or name in timelines:
                continue
            present = len(column) - column.null_count
            entry["components"][name] = entry["components"].get(name, 0) + present
        if rows and not chunk.is_static:
            def timeline(name):
                if name not in timelines:
                    return [None] * batch.num_rows
                column = batch.column(batch.schema.get_field_index(name))
                return column.cast(pa.int64()).to_pylist()

            entry["index"].extend(
                [list(r) for r in zip(timeline("step"), timeline("sim_time"), timeline("wall_time"))]
            )
        if rows and "TextLog:text" in batch.schema.names:
            texts = batch.column(batch.schema.get_field_index("TextLog:text")).to_pylist()
            for cell in texts:
                # One list of strings per row (null: no text in that row).
                entry["texts"].extend(cell or [])
        if "step" in timelines and batch.num_rows > 0:
            steps = batch.column(batch.schema.get_field_index("step")).cast(pa.int64())
            lo, hi = pc.min(steps).as_py(), pc.max(steps).as_py()
            if lo is not None:
                old = entry["step_range"]
                entry["step_range"] = [lo, hi] if old is None else [min(old[0], lo), max(old[1], hi)]

    for entry in entities.values():
        entry["timelines"] = sorted(entry["timelines"])
        if rows:
            entry["index"].sort(key=lambda r: [(v is None, v or 0) for v in r])

    print(
        json.dumps(
            {
                "rerun_version": rr.__version__,
                "verify": {"ok": verify.returncode == 0, "output": (verify.stdout + verify.stderr)[-4000:]},
                "recordings": len(recordings),
                "blueprints": len(blueprints),
                "entities": entities,
            },
            indent=1,
            sort_keys=True,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
