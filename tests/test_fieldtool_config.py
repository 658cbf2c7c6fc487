"""Field tool: `roadwatch config validate | show | diff | apply` and the atomic writer."""

from __future__ import annotations

import json
import os
import tomllib

import pytest
import tomli_w
from click.testing import CliRunner

from fieldtool_sites import site_dict
from tools.cli import cli
from tools.fieldtool.common import atomic_write

NO_SERVICE = ["--url", "http://127.0.0.1:9"]


def _write(path, data):
    path.write_text(tomli_w.dumps(data))
    return path


def test_validate_good_and_bad(tmp_path) -> None:
    good = _write(tmp_path / "good.toml", site_dict())
    bad_data = site_dict()
    bad_data["loops"][1]["channel"] = 1
    bad = _write(tmp_path / "bad.toml", bad_data)
    r = CliRunner()
    res = r.invoke(cli, ["config", "validate", str(good)])
    assert res.exit_code == 0 and "ok" in res.output and "channels [1, 2]" in res.output
    res = r.invoke(cli, ["config", "validate", str(good), str(bad)])
    assert res.exit_code == 1
    assert "INVALID" in res.output and "loops[1].channel" in res.output


def test_show_effective_and_section(tmp_path) -> None:
    good = _write(tmp_path / "good.toml", site_dict())
    res = CliRunner().invoke(cli, ["config", "show", "-c", str(good), "--section", "loops", "--json"])
    assert res.exit_code == 0, res.output
    loops = json.loads(res.output)["loops"]
    assert loops[1]["length_m"] == 1.8  # a default filled in
    assert len(loops[0]["polygon_m"]) >= 4  # derived geometry shown
    res = CliRunner().invoke(cli, ["config", "show", "-c", str(good), "--section", "nope"])
    assert res.exit_code != 0 and "no section 'nope'" in res.output


def test_diff_names_changed_keys(tmp_path) -> None:
    a = _write(tmp_path / "a.toml", site_dict())
    d = site_dict()
    d["loops"][0]["channel"] = 5
    d["source"]["fps"] = 30.0
    b = _write(tmp_path / "b.toml", d)
    res = CliRunner().invoke(cli, ["config", "diff", str(b), str(a)])
    assert res.exit_code == 0
    assert "~ loops[0].channel: 1 -> 5" in res.output and "~ source.fps: 25.0 -> 30.0" in res.output
    res = CliRunner().invoke(cli, ["config", "diff", str(a), str(a)])
    assert "no differences" in res.output


def test_apply_never_replaces_good_with_bad(tmp_path) -> None:
    target = _write(tmp_path / "config.toml", site_dict())
    good_bytes = target.read_bytes()
    bad = site_dict()
    bad["lanes"][0]["polygon_m"] = [[-3.5, 2], [0, 2], [0, 48], [-3.5, 48]]  # below the image
    badp = _write(tmp_path / "bad.toml", bad)
    res = CliRunner().invoke(cli, ["config", "apply", str(badp), "-c", str(target)] + NO_SERVICE)
    assert res.exit_code != 0 and "lanes[0]" in res.output and "not applied" in res.output
    assert target.read_bytes() == good_bytes
    assert not (tmp_path / "config.toml.last-good").exists()
    new = site_dict()
    new["site"]["name"] = "renamed"
    newp = _write(tmp_path / "new.toml", new)
    newp.write_text("# installer's note: lane 2 re-striped 2026-01\n" + newp.read_text())
    res = CliRunner().invoke(cli, ["config", "apply", str(newp), "-c", str(target)] + NO_SERVICE)
    assert res.exit_code == 0, res.output
    assert "~ site.name" in res.output and "not running" in res.output
    assert tomllib.loads(target.read_text())["site"]["name"] == "renamed"
    assert target.read_text().startswith("# installer's note")  # written verbatim, comments kept
    assert (tmp_path / "config.toml.last-good").read_bytes() == good_bytes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "config.toml", "config.toml.last-good", "new.toml"]
    res = CliRunner().invoke(cli, ["config", "apply", str(newp), "-c", str(tmp_path / "nodir" / "config.toml"), "--force"]
                             + NO_SERVICE)
    assert res.exit_code == 1 and "cannot write" in res.output and "nodir" in res.output


def test_validate_warns_about_a_missing_source_file(tmp_path) -> None:
    d = site_dict()
    d["source"]["url"] = "clips/cam.mp4"
    p = _write(tmp_path / "site.toml", d)
    res = CliRunner().invoke(cli, ["config", "validate", str(p)])
    assert res.exit_code == 0 and "WARNING" in res.output and "cam.mp4" in res.output
    (tmp_path / "clips").mkdir()
    (tmp_path / "clips" / "cam.mp4").write_bytes(b"")
    res = CliRunner().invoke(cli, ["config", "validate", str(p)])
    assert "WARNING" not in res.output


def test_atomic_write_keeps_old_content_on_failure(tmp_path) -> None:
    p = tmp_path / "f.txt"
    atomic_write(p, "old")
    os.chmod(p, 0o600)

    class Boom:
        def encode(self, _):
            raise RuntimeError("boom")

    with pytest.raises(Exception):
        atomic_write(p, b"x" * 10 + Boom())  # type: ignore[operator]
    atomic_write(p, "new")
    assert p.read_text() == "new" and (p.stat().st_mode & 0o777) == 0o600
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "missing-dir" / "f.txt", "x")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f.txt"]
