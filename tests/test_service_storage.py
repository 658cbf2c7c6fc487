"""Disk full (SQLite refuses to grow: the real SQLITE_FULL error path): the service keeps
processing and publishing, raises the STORAGE fault, and stores everything once space returns."""

from __future__ import annotations

import appliance.service as service_module
from appliance.config import load_site
from appliance.service import Service
from appliance.store import Store
from appliance.types import HealthFault
from test_service_sitefiles import cdnet_site
from tools.service_cmd import make_hooks

LIFT_AT_FRAME = 120


class _DiskFills(Service):
    """The store may not grow beyond its size at start until frame LIFT_AT_FRAME."""

    def _open_store(self) -> None:
        super()._open_store()
        pages = self.store.db.execute("PRAGMA page_count").fetchone()[0]
        self.store.db.execute(f"PRAGMA max_page_count={pages}")

    saw_storage_fault = False

    def _process(self, frame) -> None:
        if frame.seq == LIFT_AT_FRAME:
            self.full_seq = self.period_seq
            self.store.db.execute("PRAGMA max_page_count=1073741823")
        super()._process(frame)
        if frame.seq < LIFT_AT_FRAME:
            self.saw_storage_fault |= self.health.active(HealthFault.STORAGE)


def _dump(path) -> tuple:
    st = Store(path, readonly=True)
    periods = [{k: v for k, v in r.items() if k != "written_wall"} for r in st.periods()]
    events = [{k: v for k, v in r.items() if k != "id"} for r in st.loop_events()]
    return periods, events, [(h["fault"], h["active"]) for h in st.health_events()]


def test_disk_full_keeps_publishing_and_catches_up(tmp_path, shared_data, monkeypatch) -> None:
    monkeypatch.setattr(service_module, "STORE_RETRY_S", 0.0)
    (tmp_path / "ref").mkdir()
    (tmp_path / "full").mkdir()
    ref_site = load_site(cdnet_site(tmp_path / "ref", shared_data, frames=200, period_s=2))
    Service(ref_site, make_hooks(ref_site)).run()
    site = load_site(cdnet_site(tmp_path / "full", shared_data, frames=200, period_s=2))
    svc = _DiskFills(site, make_hooks(site))
    svc.run()
    assert svc.frames == 200
    assert svc.saw_storage_fault  # raised while the disk was full ...
    assert svc.full_seq >= 2  # ... while periods kept being published to the controller
    assert "STORAGE" not in svc.health.names()
    ref_periods, ref_events, _ = _dump(tmp_path / "ref" / "store.sqlite")
    periods, events, health = _dump(tmp_path / "full" / "store.sqlite")
    assert periods == ref_periods  # nothing lost, nothing doubled once space returned
    assert events == ref_events
    assert ("STORAGE", 1) in health and health.index(("STORAGE", 1)) < health.index(("STORAGE", 0))
