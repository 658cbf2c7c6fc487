"""Field tool: every command has help with an example; snapshot from real sources to PNG."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner

from fieldtool_sites import site_dict
from tools.cli import COMMANDS, cli

FIELD_COMMANDS = sorted(n for n, (mod, _, _) in COMMANDS.items() if mod.startswith("tools.fieldtool."))
SUBCOMMANDS = [["config", "validate"], ["config", "show"], ["config", "diff"], ["config", "apply"],
               ["zones", "lane"], ["zones", "loop"], ["zones", "fiducials"], ["zones", "render"], ["zones", "check"],
               ["zones", "remove"]]


@pytest.mark.parametrize("args", [[n] for n in FIELD_COMMANDS] + SUBCOMMANDS, ids=" ".join)
def test_help_has_an_example(args) -> None:
    res = CliRunner().invoke(cli, args + ["--help"])
    assert res.exit_code == 0, res.output
    assert "Example" in res.output and "roadwatch " + args[0] in res.output


def _clip_site(tmp_path, shared_data) -> tuple:
    import json

    counts = json.loads((shared_data / "cdnet-highway" / "counts.json").read_text())
    site = {
        "site": {"name": "cdnet"},
        "source": {"url": f"images:{shared_data / 'cdnet-highway' / 'input' / 'in%06d.jpg'}",
                   "width": 320, "height": 240, "fps": 25.0},
        "calibration": {"image_px": counts["calibration"]["image_px"], "road_m": counts["calibration"]["road_m"]},
        "lanes": [{"id": ln["id"], "direction": ln["direction"], "polygon_px": ln["polygon_px"]} for ln in counts["lanes"]],
        "loops": [{"id": "L1", "lane": 1, "channel": 1, "y_m": 6.34, "length_m": 4.5},
                  {"id": "L2", "lane": 2, "channel": 2, "y_m": 6.34, "length_m": 4.5}],
    }
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps(site))
    return p, counts


def test_snapshot_from_real_image_sequence(tmp_path, shared_data) -> None:
    site, counts = _clip_site(tmp_path, shared_data)
    out = tmp_path / "snap.png"
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(site), "-o", str(out), "--skip", "5"])
    assert res.exit_code == 0, res.output
    got = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    def frame(i):
        return cv2.cvtColor(cv2.imread(str(shared_data / "cdnet-highway" / "input" / f"in{i + 1:06d}.jpg")), cv2.COLOR_BGR2GRAY)

    assert got.shape == (240, 320)
    assert np.abs(got.astype(int) - frame(5)).max() <= 1  # frame 5 (0-based), same grey conversion
    assert np.abs(got.astype(int) - frame(0)).mean() > 1  # and not the first frame
    # overlay on the real frame: the lane polygons of the hand count are green-tinted inside
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(site), "-o", str(out), "--overlay"])
    assert res.exit_code == 0, res.output
    img = cv2.imread(str(out)).astype(int)
    u, v = 60, 225  # inside lane 1 near the image bottom (polygon_px of counts.json)
    assert img[v, u, 1] > img[v, u, 0] + 20 and img[v, u, 1] > img[v, u, 2] + 20


def test_snapshot_errors_are_clear(tmp_path) -> None:
    d = site_dict()
    d["source"]["url"] = "nothere.mp4"
    p = tmp_path / "site.toml"
    p.write_text(tomli_w.dumps(d))
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(p), "-o", str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "nothere.mp4" in res.output and "does not exist" in res.output
    assert not (tmp_path / "x.png").exists()
    res = CliRunner().invoke(cli, ["snapshot", "-c", str(tmp_path / "missing.toml")])
    assert res.exit_code != 0 and "missing.toml" in res.output
