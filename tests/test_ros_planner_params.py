"""The roadmap server's planner and replan settings as ROS parameters, in process with real rclpy, driven through the
node's standard parameter services (rcl_interfaces DescribeParameters / SetParameters) from a client node: each
parameter is declared as the settings' own specs say (``parameter_specs()``, ``ReplanSettings.specs()``); setting
``scoring.alpha`` on the running server weighs and plans as a planner the test makes with that alpha itself; an
unset alpha is the variant's default; a value out of range or outside the choices is refused with a reason naming
the dotted setting, and the node keeps running; a bad value given at start-up makes the node refuse to configure
instead of crashing."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_core.planning.replanner import ReplanSettings  # noqa: E402
from psprm_core.planning.settings import DEFAULT_ALPHA, PSPRMSettings, parameter_specs  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

N_NODES = 300
PARAMS = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "roadmap.n_nodes": N_NODES, "seed": 0,
          "publish_markers": False, "autostart": False, "start_problem": "south_to_either"}
#: the planner settings the server must declare: every live one and the roadmap-shaping ones it exposes
BUILD = ("roadmap.n_nodes", "seed", "edges.collision_padding")


def _call(node, srv_type, name, request, timeout=60.0):
    cl = node.create_client(srv_type, name)
    assert cl.wait_for_service(timeout_sec=10.0), f"no service {name}"
    fut = cl.call_async(request)
    done = threading.Event()
    fut.add_done_callback(lambda f: done.set())
    assert done.wait(timeout), f"{name}: no answer"
    node.destroy_client(cl)
    return fut.result()


def _set(node, **values):
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    req = SetParameters.Request()
    req.parameters = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
    return _call(node, SetParameters, "/roadmap_server/set_parameters", req).results


def _describe(node, names):
    from rcl_interfaces.srv import DescribeParameters

    req = DescribeParameters.Request(names=list(names))
    return dict(zip(names, _call(node, DescribeParameters, "/roadmap_server/describe_parameters", req).descriptors))


def _get(node, names):
    from rcl_interfaces.srv import GetParameters

    req = GetParameters.Request(names=list(names))
    return dict(zip(names, _call(node, GetParameters, "/roadmap_server/get_parameters", req).values))


def _transition(node, tid) -> bool:
    from lifecycle_msgs.srv import ChangeState

    req = ChangeState.Request()
    req.transition.id = tid
    return _call(node, ChangeState, "/roadmap_server/change_state", req, timeout=300.0).success


def _state(node) -> str:
    from lifecycle_msgs.srv import GetState

    return _call(node, GetState, "/roadmap_server/get_state", GetState.Request()).current_state.label


def _descriptor_facts(d) -> dict:
    rng = None
    if d.floating_point_range:
        rng = (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value)
    elif d.integer_range:
        rng = (d.integer_range[0].from_value, d.integer_range[0].to_value)
    return {"description": d.description, "read_only": d.read_only, "range": rng,
            "constraints": d.additional_constraints}


def test_settings_are_declared_from_their_specs():
    from rcl_interfaces.msg import ParameterType

    specs = [s for s in parameter_specs() if s.live or s.name in BUILD]
    replan = [s for s in ReplanSettings.specs() if s.live]
    assert any(s.name == "scoring.alpha" for s in specs) and len(replan) >= 10
    with InProcessSuite(PARAMS, domain_id=claim_domain_id(), nodes=("server",), autostart=False) as s:
        obs = s.probe.node
        got = _describe(obs, [sp.name for sp in specs + replan])
        values = _get(obs, [sp.name for sp in specs if sp.name != "scoring.alpha"])
        for sp in specs + replan:
            f = _descriptor_facts(got[sp.name])
            assert f["description"] == sp.description, sp.name
            assert f["read_only"] == (not sp.live), sp.name
            if sp.range is None or sp.range == (None, None) or sp.type not in (int, float):
                assert f["range"] is None, sp.name
            else:  # a bound of the spec is the descriptor's; no bound, a range past any value
                lo, hi = sp.range
                assert f["range"][0] == lo if lo is not None else f["range"][0] <= -2**62, sp.name
                assert f["range"][1] == hi if hi is not None else f["range"][1] >= 2**62, sp.name
            if sp.choices is not None:
                for c in sp.choices:
                    assert str(c) in f["constraints"], sp.name
        # the unset alpha is declared typed, without a value: no sentinel
        assert got["scoring.alpha"].type == ParameterType.PARAMETER_DOUBLE
        from rcl_interfaces.srv import GetParameters

        alpha = _call(obs, GetParameters, "/roadmap_server/get_parameters",
                      GetParameters.Request(names=["scoring.alpha"]))
        assert all(v.type == ParameterType.PARAMETER_NOT_SET for v in alpha.values)
        assert s.server.node.get_parameter_or("scoring.alpha").value is None and s.server.p["scoring.alpha"] is None
        assert not s.server.node.has_parameter("alpha")
        # the server's roadmap size as given, its padding its own default
        assert values["roadmap.n_nodes"].integer_value == N_NODES
        assert values["edges.collision_padding"].double_value == pytest.approx(0.05)


def test_alpha_set_live_plans_as_a_planner_made_with_it(tmp_path):
    from lifecycle_msgs.msg import Transition

    from psprm_core.planning.factory import make_planner, problem_configurations

    roadmap = tmp_path / "roadmap.npz"
    with InProcessSuite(dict(PARAMS, roadmap_file=str(roadmap)), domain_id=claim_domain_id(), nodes=("server",),
                        autostart=False) as s:
        obs = s.probe.node
        assert _transition(obs, Transition.TRANSITION_CONFIGURE)
        server = s.server
        scene, robot = server.scene, server.robot
        start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
        assert roadmap.is_file()

        def own(**settings):
            """A planner the test makes itself, on the roadmap the server saved, with ``settings`` given directly."""
            p = make_planner("neural-psprm-line", scene, list(server.targets), robot=robot,
                             options={"roadmap.n_nodes": N_NODES, "seed": 0, "edges.collision_padding": 0.05,
                                      **settings})
            p.load(roadmap)
            return p

        ids = server.planner.roadmap_edge_ids()

        def weights(p):
            return np.asarray(p.graph.weights)[ids].copy()

        def route(p):
            r = p.plan(start, goals, timing=False)
            assert r.success, r.reason
            return np.asarray(r.waypoints)

        # unset alpha: the variant's default for the objective (the surrogate's entry of the table)
        objective = server.planner.settings.scoring.objective
        assert server.planner.settings.scoring.alpha == DEFAULT_ALPHA[(objective, "neural")]
        default = own()
        np.testing.assert_allclose(weights(server.planner), weights(default), rtol=1e-5, atol=1e-6)
        # still unset, another objective: that objective's default alpha
        other = "eq2" if objective == "motion" else "motion"
        r = _set(obs, **{"scoring.objective": other})
        assert r[0].successful, r[0].reason
        assert s.probe.wait_for(lambda: server.planner.settings.scoring.objective == other, 10)
        assert server.planner.settings.scoring.alpha == DEFAULT_ALPHA[(other, "neural")]
        theirs = own(**{"scoring.objective": other})
        assert s.probe.wait_for(lambda: np.allclose(weights(server.planner), weights(theirs)), 10)
        r = _set(obs, **{"scoring.objective": objective})
        assert r[0].successful and s.probe.wait_for(lambda: server.planner.settings.scoring.objective == objective, 10)
        # alpha through the parameter service: the server's planner weighs and plans as one made with it
        r = _set(obs, **{"scoring.alpha": 0.0})
        assert r[0].successful, r[0].reason
        assert s.probe.wait_for(lambda: server.planner.settings.scoring.alpha == 0.0, 10)
        zero = own(**{"scoring.alpha": 0.0})
        assert not np.allclose(weights(default), weights(zero))  # the change is one that matters
        assert s.probe.wait_for(lambda: np.allclose(weights(server.planner), weights(zero)), 10)
        np.testing.assert_allclose(route(server.planner), route(zero), atol=1e-6)
        # refused: out of range, not a choice, a setting that needs a rebuild; each names the dotted setting
        for bad, word in (({"scoring.alpha": 1.5}, "scoring.alpha"), ({"scoring.objective": "fastest"},
                                                                      "scoring.objective"),
                          ({"query.heuristic": 3}, "query.heuristic"), ({"roadmap.n_nodes": 50}, "roadmap.n_nodes"),
                          ({"query.route_searches": "eq2@2"}, "query.route_searches")):
            r = _set(obs, **bad)
            assert not r[0].successful and word in r[0].reason, (bad, r[0].reason)
        assert _state(obs) == "inactive" and server.planner.settings.scoring.alpha == 0.0
        # the node keeps taking good values: the objective, with an alpha of its own
        r = _set(obs, **{"scoring.objective": "eq2", "scoring.alpha": 0.5})
        assert all(x.successful for x in r), [x.reason for x in r]
        assert s.probe.wait_for(lambda: server.planner.settings.scoring.objective == "eq2"
                                and server.planner.settings.scoring.alpha == 0.5, 10)
        mine = own(**{"scoring.objective": "eq2", "scoring.alpha": 0.5})
        assert s.probe.wait_for(lambda: np.allclose(weights(server.planner), weights(mine)), 10)
        np.testing.assert_allclose(route(server.planner), route(mine), atol=1e-6)
        # a live replan setting goes into the replanner's settings
        r = _set(obs, goal_commit_growth=0.5)
        assert not r[0].successful and "goal_commit_growth" in r[0].reason
        r = _set(obs, target_move_m=0.4)
        assert r[0].successful
        assert s.probe.wait_for(lambda: server.rp.settings.target_move_m == 0.4, 10)


@pytest.mark.parametrize("bad, word", [({"scoring.objective": "fastest"}, "scoring.objective"),
                                       ({"roadmap.n_nodes": 1}, "roadmap.n_nodes"),
                                       ({"goal_commit_growth": 0.5}, "goal_commit_growth")])
def test_a_bad_value_at_start_up_is_a_refused_configure_not_a_crash(bad, word):
    from lifecycle_msgs.msg import Transition

    with InProcessSuite(dict(PARAMS, **bad), domain_id=claim_domain_id(), nodes=("server",), autostart=False) as s:
        obs = s.probe.node
        assert _state(obs) == "unconfigured"
        assert not _transition(obs, Transition.TRANSITION_CONFIGURE)
        assert _state(obs) == "unconfigured" and s.server.planner is None
        assert word in s.server.node.configure_refusal


def test_live_settings_resolve_an_unset_alpha_to_the_variant_default():
    from psprm_ros.planner_setup import resolve_live_settings

    s = PSPRMSettings().changed({"scoring.objective": "eq2", "scoring.alpha": 0.3})
    assert resolve_live_settings(s, {"scoring.alpha": 0.6}, "psprm-line").scoring.alpha == 0.6
    unset = resolve_live_settings(s, {"scoring.alpha": None, "scoring.objective": "motion"}, "psprm-line")
    assert unset.scoring.alpha == DEFAULT_ALPHA[("motion", "oracle")]
    assert resolve_live_settings(s, {"query.connect_k": 20}, "psprm-line").scoring.alpha == 0.3


def test_a_bare_setting_name_is_named_on_the_log_with_its_dotted_path(capfd):
    """A params file that gives ``alpha`` (not ``scoring.alpha``): rclpy ignores an undeclared parameter, so the
    server says on its log which dotted name the value was meant for, and alpha stays unset. Judged from the
    process's console output (rcutils writes every log line to stderr; /rosout delivery to an in-process probe was
    not reliable inside the full suite)."""
    from lifecycle_msgs.msg import Transition

    capfd.readouterr()
    with InProcessSuite(dict(PARAMS, alpha=0.9, adapter="stretch2"), domain_id=claim_domain_id(), nodes=("server",),
                        autostart=False) as s:
        assert _transition(s.probe.node, Transition.TRANSITION_CONFIGURE)
        err = ""
        for _ in range(50):
            err += capfd.readouterr().err
            if "'scoring.alpha'" in err:
                break
            threading.Event().wait(0.1)
        lines = [ln for ln in err.splitlines() if "'alpha'" in ln and "'scoring.alpha'" in ln]
        assert lines and all("[WARN]" in ln and "[roadmap_server]" in ln for ln in lines), err[-2000:]
        assert s.server.node.get_parameter_or("scoring.alpha").value is None
        # names every node shares and this one does not declare (the adapter's) are not warned about
        assert not any("'adapter'" in ln and "is not a parameter" in ln for ln in err.splitlines())
