"""The plan digest's comparison: what it must flag between two records of fixed-seed plans."""

import copy

from psprm_core.commands.digest import compare


def _record():
    plan = {"problem": "p", "success": True, "reason": "ok", "path": [0, 4, 2], "cost": 1.5, "mean_score": 0.4,
            "waypoints": [[0.0, 0.0, 0.0], [1.0, 0.5, 0.2]], "duration": 3.0}
    return {"scenes": [{"scene": "home", "nodes": 10, "edges": 30, "plans": [plan]}]}


def test_identical_records_agree():
    assert compare(_record(), _record()) == []


def test_each_kind_of_change_is_flagged():
    for key, value in [("path", [0, 3, 2]), ("cost", 1.5 + 1e-5), ("duration", 3.1), ("success", False),
                       ("waypoints", [[0.0, 0.0, 0.0], [1.0, 0.5, 0.2 + 1e-5]])]:
        new = _record()
        new["scenes"][0]["plans"][0][key] = value
        assert compare(new, _record()), key
    new = copy.deepcopy(_record())
    new["scenes"][0]["edges"] = 31
    assert compare(new, _record())


def test_durations_in_reasons_are_not_compared():
    a, b = _record(), _record()
    for r, t in ((a, "0.3"), (b, "0.4")):
        r["scenes"][0]["plans"][0].update(success=False, reason=f"no way out ({t} s, 5.39 m)")
    assert compare(a, b) == []
    b["scenes"][0]["plans"][0]["reason"] = "no way out (0.4 s, 5.40 m)"
    assert compare(a, b)
