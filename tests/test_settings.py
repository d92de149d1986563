"""PS-PRM settings in one place: every field's metadata (description, range or choices, per-query, live, build),
the parameter specs made from it, and what the code derives from it (query options, the roadmap fingerprint)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from psprm_core.errors import ConfigError
from psprm_core.planning.settings import PSPRMSettings, RouteSearch, parameter_specs, query_only_settings


def _other_value(spec):
    """A valid value of ``spec`` other than its default (chosen from its type, range and choices)."""
    if spec.choices is not None:
        return next(c for c in spec.choices if c != spec.default)
    if spec.type is bool:
        return not spec.default
    if spec.type is tuple:  # query.route_searches
        return (RouteSearch("alt"),)
    lo, hi = spec.range if spec.range is not None else (None, None)
    if spec.default is None:  # unset (scoring.alpha): a value inside the range
        return spec.type(0.5 * (lo + hi))
    step = 1 if spec.type is int else 0.25
    up = spec.default + step
    value = up if hi is None or up <= hi else spec.default - step
    assert (lo is None or value >= lo) and (hi is None or value <= hi), spec
    return spec.type(value)


def _nested(flat: dict) -> dict:
    out: dict = {}
    for name, value in flat.items():
        *groups, leaf = name.split(".")
        node = out
        for g in groups:
            node = node.setdefault(g, {})
        node[leaf] = value
    return out


def test_every_setting_has_a_spec_with_a_description():
    """The specs cover every field of every group (counted from the dataclasses here), each once, named by its
    dotted path, with a description and the right Python type."""
    s = PSPRMSettings()
    names = []
    for group in dataclasses.fields(s):
        value = getattr(s, group.name)
        if dataclasses.is_dataclass(value):
            names += [f"{group.name}.{f.name}" for f in dataclasses.fields(value)]
        else:
            names.append(group.name)
    specs = parameter_specs()
    assert [sp.name for sp in specs] == names
    for sp in specs:
        assert sp.description.strip(), sp.name
        assert sp.type in (bool, int, float, str, tuple), sp
        assert isinstance(sp.default, sp.type) or (sp.default is None and sp.name == "scoring.alpha"), sp
    by_name = {sp.name: sp for sp in specs}
    # spot checks against the planner's documented behaviour
    assert by_name["scoring.alpha"].range == (0.0, 1.0) and by_name["scoring.alpha"].live
    assert by_name["visibility.constraint"].choices == ("line", "frustum") and not by_name["visibility.constraint"].live
    assert not by_name["edges.collision_padding"].live  # PSPRM.update_settings refuses it
    assert by_name["query.heuristic"].query and not by_name["query.connect_k"].query


def test_specs_round_trip_through_settings_and_yaml(tmp_path):
    """The specs' defaults, given as dotted changes or written as a nested YAML file, make the default settings,
    which validate."""
    specs = parameter_specs()
    defaults = {sp.name: sp.default for sp in specs}
    assert PSPRMSettings().changed(defaults) == PSPRMSettings()
    path = tmp_path / "all.yaml"
    path.write_text(yaml.safe_dump(_nested({k: list(v) if isinstance(v, tuple) else v for k, v in defaults.items()})))
    loaded = PSPRMSettings.from_yaml(path)
    assert loaded == PSPRMSettings()
    loaded.validate()
    # every spec's other value is accepted and lands in its own field only
    for sp in specs:
        s = PSPRMSettings().changed({sp.name: _other_value(sp)})
        s.validate()
        assert s.value(sp.name) == _other_value(sp) != sp.default


def test_values_outside_a_range_or_choice_are_config_errors_naming_the_dotted_field():
    """Below the lower bound, above the upper one, NaN, the wrong type, or a string not among the choices: each a
    ConfigError whose field is the dotted name."""
    checked = 0
    for sp in parameter_specs():
        bad = []
        if sp.range is not None:
            lo, hi = sp.range
            if lo is not None:
                bad.append(sp.type(lo - 1))
            if hi is not None:
                bad.append(sp.type(hi + 1))
            if sp.type is float:
                bad.append(float("nan"))
            bad.append("many")
        if sp.choices is not None:
            bad.append("no_such_choice")
        for value in bad:
            with pytest.raises(ConfigError) as e:
                PSPRMSettings().changed({sp.name: value}).validate("here")
            assert e.value.field == sp.name and e.value.source == "here", (sp.name, value, e.value)
            checked += 1
    assert checked > 60


def test_query_only_settings_leave_the_built_roadmap_as_it_is(home_tv_planner):
    """Each setting that the roadmap's fingerprint leaves out, changed before the build, builds the same roadmap
    (nodes, edges, their Eq. 1 perception and motion costs, the node scores) as the defaults; a changed seed, which
    the fingerprint keeps, builds another one (the comparison can tell)."""
    def roadmap(**settings):
        _, _, p, *_ = home_tv_planner(**settings)
        g = p.graph
        e = g.valid_edge_ids()
        return p.fingerprint(), (g.configs[p.roadmap_node_ids()], np.stack([g.edge_u[e], g.edge_v[e]]),
                                 g.edge_attribute("c_p")[e], g.edge_attribute("c_m")[e], p.pipeline.rm.node_scores)

    def same(a, b):
        return all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, b))

    base = {"roadmap.n_nodes": 60, "seed": 1}
    fp0, ref = roadmap(**base)
    query_only = set(query_only_settings())
    specs = [sp for sp in parameter_specs() if sp.name.rpartition(".")[2] in query_only]
    assert len(specs) == 25
    for sp in specs:
        fp, got = roadmap(**base, **{sp.name: _other_value(sp)})
        assert same(got, ref), sp.name
        assert fp == fp0, sp.name
    fp, got = roadmap(**{**base, "seed": 2})
    assert not same(got, ref) and fp != fp0


def test_alpha_unset_is_the_variants_default_for_the_objective(load_robot, tmp_path):
    """alpha left unset: Eq. 2 the paper's (0.75 with the oracle, 0.8 with the surrogate), the motion-weighted
    objective 0.95 (docs/benchmarks.md, "Perception gain"), a planner made without a variant the surrogate's Eq. 2
    value; alpha given (as an override, in a settings file) wins."""
    from psprm_core.paths import resolve_named
    from psprm_core.perception.scoring import GeometricScorer
    from psprm_core.planning.factory import make_planner
    from psprm_core.planning.psprm import PSPRM
    from psprm_core.scene import load_scene

    paper = {("eq2", "oracle"): 0.75, ("eq2", "neural"): 0.8, ("motion", "oracle"): 0.95, ("motion", "neural"): 0.95}
    assert PSPRMSettings().scoring.alpha is None
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    for (objective, kind), alpha in paper.items():
        variant = "neural-psprm-line" if kind == "neural" else "psprm-line"
        p = make_planner(variant, scene, ["tv"], robot=robot,
                         options={"roadmap.n_nodes": 50, "scoring.objective": objective})
        assert p.settings.scoring.alpha == alpha, (objective, kind)
    p = make_planner("psprm-line", scene, ["tv"], robot=robot,
                     options={"roadmap.n_nodes": 50, "scoring.objective": "eq2", "scoring.alpha": 0.4})
    assert p.settings.scoring.alpha == 0.4
    path = tmp_path / "p.yaml"
    path.write_text("scoring:\n  objective: motion\n  alpha: 0.6\n")
    p = make_planner("neural-psprm-line", scene, ["tv"], robot=robot, settings=PSPRMSettings.from_yaml(path))
    assert p.settings.scoring.alpha == 0.6
    path.write_text("scoring:\n  alpha: null\n")
    assert PSPRMSettings.from_yaml(path).scoring.alpha is None
    for objective in ("eq2", "motion"):
        p = PSPRM(robot, scene, GeometricScorer(scene, "tv", robot.config.intrinsics), scene.target("tv").center,
                  PSPRMSettings().changed({"scoring.objective": objective}))
        assert p.settings.scoring.alpha == 0.8
        p.update_settings(p.settings.changed({"scoring.alpha": None, "query.shortcut": True}))
        assert p.settings.scoring.alpha == 0.8 and p.settings.query.shortcut  # unset: the planner keeps its alpha


def test_route_searches_are_typed_and_read_from_their_text_forms(tmp_path):
    """query.route_searches holds RouteSearch entries; a comma separated string or a list of entries (settings
    changes, YAML, --set) becomes the same tuple; a bad entry is a ConfigError naming the field and the entry."""
    from psprm_core.baselines import parse_settings

    want = (RouteSearch("eq2", 0.8), RouteSearch("alt", 1.0), RouteSearch("motion", 1.0))
    s = PSPRMSettings().changed({"query.route_searches": " eq2@0.8, alt ,motion@1"})
    assert s.query.route_searches == want and s.route_search_list() == want
    assert [str(r) for r in want] == ["eq2@0.8", "alt", "motion@1"]
    assert PSPRMSettings().changed({"query.route_searches": ["eq2@0.8", "alt", RouteSearch("motion", 1.0)]}) == s
    assert PSPRMSettings().changed({"query.route_searches": ""}).query.route_searches == ()
    for text in ("query:\n  route_searches: eq2@0.8,alt,motion@1\n",
                 "query:\n  route_searches: [eq2@0.8, alt, motion@1.0]\n"):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        assert PSPRMSettings.from_yaml(path).query.route_searches == want
    got = parse_settings(["query.route_searches=eq2@0.8,alt,motion@1"], PSPRMSettings, "psprm")
    assert list(got.values()) == [want]
    for bad in ("eq2", "hops@0.5", "eq2@1.5", "eq2@x", "alt@0.3", "motion@nan"):
        with pytest.raises(ConfigError, match=rf"query\.route_searches.*'{bad}'"):
            PSPRMSettings().changed({"query.route_searches": f"alt,{bad}"})
    with pytest.raises(ConfigError, match="query.route_searches"):
        PSPRMSettings().changed({"query.route_searches": (RouteSearch("eq2", 2.0),)}).validate()
    path.write_text("query:\n  route_searches: [eq2@0.8, 3]\n")
    with pytest.raises(ConfigError, match="p.yaml.*query.route_searches"):
        PSPRMSettings.from_yaml(path)


def test_settings_are_named_by_dotted_paths_only(home_tv_planner):
    """changed, value, a query's options and --set take dotted paths; a field's own name is a ConfigError (an
    InputError for query options) that tells its dotted path, so a bare name is never taken for another field."""
    from psprm_core.baselines import parse_settings
    from psprm_core.errors import InputError, PsprmError

    s = PSPRMSettings()
    assert s.changed({"roadmap.n_nodes": 40, "seed": 4}).value("roadmap.n_nodes") == 40
    for call in (lambda: s.changed({"n_nodes": 40}), lambda: s.changed(n_nodes=40), lambda: s.value("n_nodes")):
        with pytest.raises(ConfigError, match="dotted path: 'roadmap.n_nodes'") as e:
            call()
        assert e.value.field == "n_nodes"
    with pytest.raises(ConfigError, match="unknown setting"):
        s.changed({"roadmap.no_such": 1})
    with pytest.raises(PsprmError, match="dotted path: 'query.shortcut'"):
        parse_settings(["shortcut=true"], PSPRMSettings, "psprm")
    assert parse_settings(["query.shortcut=true"], PSPRMSettings, "psprm") == {"query.shortcut": True}
    _, _, p, start, goals, _ = home_tv_planner(**{"roadmap.n_nodes": 300, "seed": 1})
    with pytest.raises(InputError, match="query.shortcut"):
        p.plan(start, goals, timing=False, options={"shortcut": True})
    with pytest.raises(InputError, match="query.heuristic"):  # not a per-query setting
        p.plan(start, goals, timing=False, options={"query.connect_k": 3})
    assert p.plan(start, goals, timing=False, options={"query.heuristic": "exact", "query.shortcut": True}).success


def test_presets_load_validate_and_hold_their_configurations(load_robot):
    """Both presets load for every shipped robot and validate; the paper preset holds the paper's configuration
    (Eq. 2, 3000 uniform nodes with 15 neighbours, N = 5, the hop heuristic, no shortcuts, no route selection, no
    escape or wide connection) and the shipped one the motion objective with shortcuts; a planner made from the
    paper preset takes the paper's alpha (0.8 with the surrogate, 0.75 with the oracle). An unknown preset is a
    ConfigError."""
    from psprm_core.paths import config_dir, resolve_named
    from psprm_core.planning.factory import PRESETS, load_preset, make_planner
    from psprm_core.scene import load_scene

    assert set(PRESETS) == {"psprm", "psprm_paper"}
    robots = sorted(p.stem for p in (config_dir() / "robots").glob("*.yaml") if "." not in p.stem)
    assert robots
    for name in PRESETS:
        assert (config_dir() / "planners" / PRESETS[name]).is_file()
        for robot in [None, *robots]:
            load_preset(name, robot).validate()
    paper = load_preset("psprm_paper")
    assert (paper.scoring.objective, paper.scoring.alpha, paper.roadmap.n_nodes, paper.roadmap.k_neighbors,
            paper.roadmap.biased_share, paper.edges.n_interp, paper.query.heuristic, paper.query.shortcut,
            paper.query.route_searches, paper.recovery.query_escape_s, paper.recovery.query_wide_k) == (
        "eq2", None, 3000, 15, 0.0, 5, "hop", False, (), 0.0, 0)
    shipped = load_preset("psprm")
    assert (shipped.scoring.objective, shipped.query.shortcut) == ("motion", True)
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    for variant, alpha in (("neural-psprm-line", 0.8), ("psprm-line", 0.75)):
        p = make_planner(variant, scene, ["tv"], robot=robot, preset="psprm_paper", options={"roadmap.n_nodes": 50})
        assert (p.settings.scoring.alpha, p.settings.scoring.objective, p.settings.roadmap.n_nodes) == (
            alpha, "eq2", 50)
    with pytest.raises(ConfigError, match="unknown preset 'nope'"):
        load_preset("nope")


def test_query_options_plan_as_the_planners_own_settings_and_fixed_settings_are_refused(home_tv_planner):
    """Each per-query setting given as a query's option plans the same route as the planner with that setting
    changed (and leaves the planner's settings as they were); the settings that are not live and that a made planner
    holds fixed (the visibility model, the collision padding) are refused by update_settings, the live ones taken."""
    from psprm_core.planning.settings import query_options

    # every edge checked at the build: a query leaves the roadmap as it is (lazy checks would change it between plans)
    _, _, p, start, goals, _ = home_tv_planner(**{"roadmap.n_nodes": 300, "seed": 1, "edges.lazy_collision": False})
    s0 = p.settings
    specs = {sp.name: sp for sp in parameter_specs()}
    assert set(query_options()) == {sp.name for sp in specs.values() if sp.query}
    values = {"query.heuristic": "exact", "query.route_searches": "eq2@0.5,alt"}
    for name in query_options():
        value = values.get(name, _other_value(specs[name]))
        # the first shortcut query of a planner returns another route than the identical queries after it: one
        # query first, so that both compared queries follow one
        p.plan(start, goals, timing=False, options={name: value})
        a = p.plan(start, goals, timing=False, options={name: value})
        assert p.settings == s0, name
        try:
            p.update_settings(s0.changed({name: value}))
            b = p.plan(start, goals, timing=False)
        finally:
            p.update_settings(s0)
        assert a.success and b.success, name
        # the query's own start and goal nodes get new ids per query: compare the route itself
        assert np.allclose(np.asarray(a.waypoints), np.asarray(b.waypoints)), name
        assert a.cost == pytest.approx(b.cost), name
    for sp in specs.values():
        if sp.name.startswith(("visibility.", "edges.collision_padding")):
            assert not sp.live
            with pytest.raises(ConfigError, match=sp.name):
                p.update_settings(s0.changed({sp.name: _other_value(sp)}))
            assert p.settings == s0
        elif sp.live and sp.name.startswith(("edges.", "scoring.", "query.", "recovery.")):
            p.update_settings(s0.changed({sp.name: _other_value(sp)}))
            p.update_settings(s0)
