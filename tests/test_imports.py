"""The library's import structure: no import cycle inside ``psprm_core`` (counting the imports inside functions,
which Python resolves late but a reader follows all the same), and the planning library never imports the
evaluation and tooling code (every module of ``psprm_core.evaluation``, the ``psprm`` commands, the CLI). Read from
the source files with ``ast``, not from what happens to be imported."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "psprm_core"

#: evaluation and tooling (these packages and everything under them): they may import the library, never the other
#: way round
EVALUATION = ("psprm_core.evaluation", "psprm_core.commands", "psprm_core.cli")


def _is_evaluation(m: str) -> bool:
    return any(m == e or m.startswith(e + ".") for e in EVALUATION)


def _modules() -> dict:
    out = {}
    for p in ROOT.rglob("*.py"):
        parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _graph() -> dict:
    mods = _modules()
    G = {m: set() for m in mods}
    for m, p in mods.items():
        package = m if p.name == "__init__.py" else m.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(p.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                names = [mod] + [f"{mod}.{a.name}" for a in node.names]
            G[m].update(n for n in names if n in mods and n != m)
    return G


def _cycles(G: dict) -> list:
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in G[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(G):
        if v not in index:
            visit(v)
    return out


def test_the_graph_reader_finds_a_planted_cycle():
    G = _graph()
    assert "psprm_core.planning.psprm" in G["psprm_core.planning.factory"]  # it reads real edges
    G = {k: set(v) for k, v in G.items()}
    G["psprm_core.geometry"].add("psprm_core.robot")  # robot imports geometry: a planted back edge
    assert any("psprm_core.geometry" in c and "psprm_core.robot" in c for c in _cycles(G))


def test_psprm_core_has_no_import_cycle():
    assert _cycles(_graph()) == []


def _library_imports_of_evaluation(G: dict) -> dict:
    bad = {m: sorted(t for t in ts if _is_evaluation(t)) for m, ts in G.items() if not _is_evaluation(m)}
    return {m: v for m, v in bad.items() if v}


def test_the_evaluation_rule_reads_the_subpackage_and_finds_a_planted_import():
    G = _graph()
    evaluation = {m for m in G if _is_evaluation(m)}
    assert {"psprm_core.evaluation", "psprm_core.evaluation.bench", "psprm_core.evaluation.reference",
            "psprm_core.commands.bench", "psprm_core.cli"} <= evaluation
    assert not any(_is_evaluation(m) for m in ("psprm_core.planning.psprm", "psprm_core.executors",
                                               "psprm_core.perception.dataset", "psprm_core.baselines.base"))
    G = {k: set(v) for k, v in G.items()}
    G["psprm_core.perception.dataset"].add("psprm_core.evaluation.bench")  # a planted library -> evaluation edge
    assert _library_imports_of_evaluation(G) == {"psprm_core.perception.dataset": ["psprm_core.evaluation.bench"]}


def test_the_library_never_imports_the_evaluation_modules():
    assert _library_imports_of_evaluation(_graph()) == {}


def test_the_library_raises_its_own_errors_for_what_a_user_can_cause():
    """No ``raise ValueError / KeyError / IndexError / FileNotFoundError`` left in psprm_core: a bad value, an unknown
    name, an index out of range, a missing file are PsprmError subclasses (which are also the built-in type), so a
    node or a CLI catches one family. Runtime failures of a computation (RuntimeError) are not input errors."""
    banned = {"ValueError", "KeyError", "IndexError", "FileNotFoundError"}
    found = []
    for p in ROOT.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and \
                    isinstance(node.exc.func, ast.Name) and node.exc.func.id in banned:
                found.append(f"{p.relative_to(ROOT.parent)}:{node.lineno} {node.exc.func.id}")
    assert found == []


def test_error_family_members_are_also_the_builtin_types():
    from psprm_core.errors import InputError, OutOfRangeError, PsprmError, UnknownNameError
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene

    scene = load_scene(resolve_named("scene", "home"))
    try:
        scene.target("mug")
    except PsprmError as exc:
        assert isinstance(exc, KeyError) and isinstance(exc, UnknownNameError)
        assert str(exc).startswith("scene 'home' has no target 'mug'")  # printed as written, not quoted
    else:
        raise AssertionError("an unknown target raised nothing")
    assert issubclass(InputError, ValueError) and issubclass(OutOfRangeError, IndexError)



#: modules a package may hold before it is split into sub-packages
MAX_MODULES_PER_PACKAGE = 15


def _oversized_packages(*roots) -> dict:
    """{folder: number of modules} of every folder under ``roots`` with more than the limit."""
    out = {}
    for root in roots:
        for d in [root, *(p for p in root.rglob("*") if p.is_dir() and p.name != "__pycache__")]:
            n = len(list(d.glob("*.py")))
            if n > MAX_MODULES_PER_PACKAGE:
                out[d] = n
    return out


def test_no_package_holds_more_than_fifteen_modules(tmp_path):
    """The layout: psprm_core and psprm_ros are split into sub-packages (planning/roadmap, planning/search, kernels,
    robots, ...) before a folder grows past fifteen modules; a planted folder of sixteen is found."""
    assert _oversized_packages(ROOT, ROOT.parent / "psprm_ros") == {}
    planted = tmp_path / "pkg" / "sub"
    planted.mkdir(parents=True)
    for i in range(MAX_MODULES_PER_PACKAGE + 1):
        (planted / f"m{i}.py").write_text("")
    assert _oversized_packages(tmp_path) == {planted: MAX_MODULES_PER_PACKAGE + 1}


MAX_MODULE_LINES = 500


def _long_modules(*roots: Path) -> dict:
    """Modules (path -> lines) of the packages under ``roots`` longer than :data:`MAX_MODULE_LINES`."""
    out = {}
    for root in roots:
        for f in sorted(root.rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            n = len(f.read_text(encoding="utf-8").splitlines())
            if n > MAX_MODULE_LINES:
                out[f] = n
    return out


def test_no_module_is_longer_than_five_hundred_lines(tmp_path):
    """The layout: a module that grows past 500 lines is split along a seam of its own; a planted long one is
    found."""
    assert _long_modules(ROOT, ROOT.parent / "psprm_ros") == {}
    planted = tmp_path / "long.py"
    planted.write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    assert _long_modules(tmp_path) == {planted: MAX_MODULE_LINES + 1}
