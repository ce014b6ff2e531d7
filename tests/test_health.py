"""The skeleton's camera watch (artrack_nodes/health.py): which cameras are silent, and what it reports."""

from __future__ import annotations

import math
from types import SimpleNamespace

from artrack.types import STATUS_LOST
from artrack_nodes.health import CameraWatch


class FakeDiag:
    def __init__(self):
        self.values, self.warnings = {}, []

    def set(self, key, value):
        self.values[key] = value

    def warn(self, message):
        self.warnings.append(message)


class FakeNode:
    def __init__(self):
        self.lines = []

    def get_logger(self):
        return SimpleNamespace(warning=lambda m: self.lines.append(("warn", m)),
                               info=lambda m: self.lines.append(("info", m)))


def test_a_camera_is_silent_only_while_another_reports():
    w = CameraWatch(["a", "b"], fps=30.0)
    assert w.silent_after_s == 1.0
    w.last, w.t_first = {"a": 10.0, "b": 10.0}, 10.0
    assert w.silent_now(10.5) == set()
    w.last = {"a": 12.0, "b": 10.0}
    assert w.silent_now(12.1) == {"b"}
    assert w.silent_now(20.0) == set(), "nobody reports: no input, not a camera fault"
    w.last, w.t_first = {"a": 12.0}, 12.0
    assert w.silent_now(12.1) == set(), "a camera that never reported: silent only after the delay"
    w.last["a"] = 13.4
    assert w.silent_now(13.5) == {"b"}
    assert CameraWatch(["a"], fps=5.0).silent_after_s == 2.0


def test_report_logs_transitions_once_and_warns_on_loss(monkeypatch):
    import artrack_nodes.health as health

    node, diag = FakeNode(), FakeDiag()
    w = CameraWatch(["a", "b"], fps=30.0)
    update = w.report(node)
    now = [100.0]
    monkeypatch.setattr(health.time, "monotonic", lambda: now[0])
    w.last, w.t_first = {"a": 100.0, "b": 98.0}, 98.0
    update(diag)
    update(diag)
    assert [m for k, m in node.lines if k == "warn"] == ["camera b silent for 2.0 s: tracking with a"]
    assert diag.values["cameras_silent"] == "b" and diag.values["cameras_reporting"] == "a"
    w.last["b"] = 100.0
    w.estimated(SimpleNamespace(status=STATUS_LOST, quality=0.2), ["a", "b"])
    update(diag)
    assert node.lines[-1] == ("info", "camera b is back")
    assert diag.values["tracking_status"] == "lost" and "body lost" in diag.warnings
    assert not math.isnan(diag.values["track_quality"])
