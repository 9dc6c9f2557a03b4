"""The package's layers, checked: imports go one way, no cycles, modules of a readable size,
long functions that say why they are one function, none over ``MAX_FN`` lines, loop state named.

Layers, bottom to top (a module may import from its own layer and the layers below):

    core       backend, keys, freeze, timing, check, io
    scene      scenes, views and rigs, the G-buffer, light sampling, the BSDF table
    reference  the ground truth, path-traced references, metrics
    osc        the on-surface cache and its contract for cache methods (requests, capabilities)
    methods    the method contract (slc.methods: the registry; slc.methods.base: Method, Param;
               slc.methods.cache_method: the cache-method base class; slc.methods.frames: the
               frame loop)
    lib        algorithms the method folders build on (cone lobes, SH and YCoCg, light integrals)
    method     one folder per method under slc/methods/ (baselines included)
    distributed  render nodes sharing one surface cache (owners, records, the Ray actors)
    run        a method's run over a sequence, experiments, jobs, the command line, benchmarks

Method folders do not import each other: the algorithms they share or build on are in ``slc/lib``;
a class in slc/methods/ has one base at most (no mixins: a method holds its parts).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "slc"

RANK = {"core": 0, "scene": 1, "reference": 2, "osc": 3, "methods": 4, "lib": 5, "method": 6, "distributed": 7,
        "run": 8}
MAX_LINES, MAX_LONG, LONG = 650, 5, 450
# a function over LONG_FN lines starts its docstring with the reason it is one function
LONG_FN, ONE_FUNCTION = 80, "one function because"
# no function in slc/ over MAX_FN lines; a dr.while_loop state holds at most MAX_STATE positional
# values (more: one named structure, a DRJIT_STRUCT dataclass)
MAX_FN, MAX_STATE = 100, 3


def _modules() -> dict[str, Path]:
    mods = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


MODULES = _modules()


def _imports(name: str, path: Path):
    """(imported slc module, imported names, line, function-level) for every import of ``name``."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    fn_nodes = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            fn_nodes.update(id(n) for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "slc":
                    yield a.name, [], node.lineno, id(node) in fn_nodes
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "slc":
                continue
            for a in node.names:
                sub = f"{mod}.{a.name}"
                yield (sub if sub in MODULES else mod), [a.name], node.lineno, id(node) in fn_nodes


def _owner(mod: str) -> str:
    while mod not in MODULES and "." in mod:
        mod = mod.rsplit(".", 1)[0]
    return mod


def _layer(mod: str) -> tuple[str, str | None]:
    """(layer, method folder or None) of a module name."""
    parts = mod.split(".")
    if len(parts) == 1:
        return "run", None             # slc/__init__.py points Dr.Jit at libLLVM: it may import core only
    top = parts[1]
    if top == "methods":       # a folder under slc/methods/ is a method; a module beside them, the contract
        return ("method", parts[2]) if len(parts) > 2 and (PKG / "methods" / parts[2]).is_dir() else ("methods", None)
    return top, None


def _graph():
    g = {}
    for name, path in MODULES.items():
        g[name] = {_owner(m) for m, _, _, _ in _imports(name, path)} - {name}
        g[name] &= set(MODULES)
    return g


def test_every_module_belongs_to_a_layer():
    bad = [m for m in MODULES if m != "slc" and _layer(m)[0] not in RANK]
    assert not bad, f"modules outside the layers {sorted(RANK)}: {bad}"


def test_imports_go_one_way():
    bad = []
    for name, deps in _graph().items():
        if name == "slc":
            continue
        layer, folder = _layer(name)
        for d in deps:
            if d == "slc":
                continue
            dl, dfolder = _layer(d)
            if RANK[dl] > RANK[layer]:
                bad.append(f"{name} ({layer}) imports {d} ({dl})")
            elif layer == dl == "method" and folder != dfolder:
                bad.append(f"{name} imports another method's module {d}")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))


def test_no_import_cycle():
    g = _graph()
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g[v]:
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
                cycles.append(sorted(comp))

    for v in g:
        if v not in index:
            visit(v)
    # a package's __init__ importing its own modules is not a cycle of the layers
    cycles = [c for c in cycles if not all(m.startswith(c[0] + ".") or m == c[0] for m in c)]
    assert not cycles, f"import cycles: {cycles}"


def test_no_private_name_imported_across_modules():
    bad = [f"{name}:{line} imports {n} from {mod}"
           for name, path in MODULES.items()
           for mod, names, line, _ in _imports(name, path)
           for n in names if n.startswith("_") and not n.startswith("__")]
    assert not bad, "\n".join(bad)


def test_function_level_imports_say_why():
    """A function-level import of a project module is there for a reason stated beside it."""
    def explained(lines, i):   # a comment on the import's line, or above its block of imports
        if "#" in lines[i]:
            return True
        while i > 0 and lines[i - 1].strip().startswith(("import ", "from ")):
            i -= 1
        return lines[i - 1].strip().startswith("#")

    bad = []
    for name, path in MODULES.items():
        lines = path.read_text().splitlines()
        for mod, _, line, fn_level in _imports(name, path):
            if fn_level and not explained(lines, line - 1):
                bad.append(f"{path.relative_to(ROOT)}:{line}: {lines[line - 1].strip()}")
    assert not bad, "function-level imports without a reason:\n" + "\n".join(sorted(set(bad)))


def _sources() -> list[Path]:
    return list(PKG.rglob("*.py")) + list((ROOT / "experiments").glob("*.py"))


def _sizes():
    return {p: len(p.read_text().splitlines()) for p in _sources()}


def test_module_sizes():
    sizes = _sizes()
    too_long = {str(p.relative_to(ROOT)): n for p, n in sizes.items() if n > MAX_LINES}
    assert not too_long, f"modules over {MAX_LINES} lines: {too_long}"
    long = {p: n for p, n in sizes.items() if n > LONG}
    assert len(long) <= MAX_LONG, (f"{len(long)} modules over {LONG} lines (at most {MAX_LONG}): "
                                   f"{sorted(str(p.relative_to(ROOT)) for p in long)}")
    unexplained = [str(p.relative_to(ROOT)) for p in long
                   if "why" not in p.read_text()[:1500].lower()]
    assert not unexplained, f"long modules that do not say at their top why they are long: {unexplained}"


def test_long_functions_say_why():
    """A function of over ``LONG_FN`` lines in slc/ or experiments/ (a traced kernel whose stages
    share many locals, say) states in the first paragraph of its docstring why it is one function,
    in a sentence with ``ONE_FUNCTION`` ("One function because ...")."""
    bad = []
    for p in sorted(_sources()):
        for fn in ast.walk(ast.parse(p.read_text())):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            n = fn.end_lineno - fn.lineno + 1
            top = " ".join((ast.get_docstring(fn) or "").split("\n\n")[0].split()).lower()
            if n > LONG_FN and ONE_FUNCTION not in top:
                bad.append(f"{p.relative_to(ROOT)}:{fn.lineno} {fn.name} ({n} lines)")
    assert not bad, (f"functions over {LONG_FN} lines whose docstring does not start with why they are one "
                     f"function ('{ONE_FUNCTION.capitalize()} ...'):\n" + "\n".join(bad))


def _package_functions():
    for p in sorted(PKG.rglob("*.py")):
        for fn in ast.walk(ast.parse(p.read_text())):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield p, fn


def test_no_function_over_max_fn():
    bad = [f"{p.relative_to(ROOT)}:{fn.lineno} {fn.name} ({fn.end_lineno - fn.lineno + 1} lines)"
           for p, fn in _package_functions() if fn.end_lineno - fn.lineno + 1 > MAX_FN]
    assert not bad, f"functions in slc/ over {MAX_FN} lines (split them into stages):\n" + "\n".join(bad)


def test_loop_state_is_named():
    """Every ``dr.while_loop`` in slc/ spells its state as a tuple of at most ``MAX_STATE``
    values, a named structure counting as one (a state built elsewhere cannot be checked)."""
    bad = []
    for p in sorted(PKG.rglob("*.py")):
        for call in ast.walk(ast.parse(p.read_text())):
            if not (isinstance(call, ast.Call) and isinstance(call.func, (ast.Attribute, ast.Name))
                    and (getattr(call.func, "attr", None) or getattr(call.func, "id", None)) == "while_loop"):
                continue
            state = next((k.value for k in call.keywords if k.arg == "state"), call.args[0] if call.args else None)
            where = f"{p.relative_to(ROOT)}:{call.lineno}"
            if not isinstance(state, ast.Tuple):
                bad.append(f"{where}: state not a tuple literal")
            elif len(state.elts) > MAX_STATE:
                bad.append(f"{where}: {len(state.elts)} positional state values")
    assert not bad, "dr.while_loop states to name (a DRJIT_STRUCT dataclass):\n" + "\n".join(bad)


@pytest.mark.parametrize("folder", sorted(p.name for p in (PKG / "methods").iterdir()
                                           if p.is_dir() and not p.name.startswith("_")))
def test_each_method_folder_registers_by_convention(folder):
    assert (PKG / "methods" / folder / "method.py").is_file(), \
        f"slc/methods/{folder}/ has no method.py (methods are found as slc/methods/<folder>/method.py)"


def test_no_mixins_in_methods():
    """A class in slc/methods/ has at most one base: a method is one class that holds its parts
    (composition: OSCGI its primary update, ReSTIR its target and reuse), not one class spread
    over base classes whose methods read attributes defined elsewhere."""
    bad = [f"{p.relative_to(ROOT)}:{c.lineno} class {c.name}({', '.join(ast.unparse(b) for b in c.bases)})"
           for p in sorted((PKG / "methods").rglob("*.py"))
           for c in ast.walk(ast.parse(p.read_text()))
           if isinstance(c, ast.ClassDef) and len(c.bases) >= 2]
    assert not bad, "classes with two or more bases (mixins; hold the parts instead):\n" + "\n".join(bad)


MAX_FN_IMPORTS = 40


def test_few_function_level_imports():
    """Imports sit at module level (importing slc chooses no Mitsuba variant, so nothing waits for
    one): at most ``MAX_FN_IMPORTS`` imports inside functions in slc/ and experiments/ together,
    for what must wait (Ray, matplotlib's backend, a slow optional import, the command line's
    commands after its variant)."""
    found = []
    for p in sorted(_sources()):
        tree = ast.parse(p.read_text())
        inner = {id(n): n for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
                 for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))}
        found += [f"{p.relative_to(ROOT)}:{n.lineno}" for n in inner.values()]
    assert len(found) <= MAX_FN_IMPORTS, f"{len(found)} function-level imports:\n" + "\n".join(sorted(found))


def test_dataclass_structs_declare_their_fields_once():
    """A dataclass used as a Dr.Jit struct (loop state, kernel inputs) gets ``DRJIT_STRUCT`` from
    its fields (``@drjit_struct``, slc/core/structs.py), not from a second list of them."""
    def names(decorators):
        return {d.id if isinstance(d, ast.Name) else getattr(d, "attr", getattr(getattr(d, "func", None), "id", None))
                for d in decorators}
    bad = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and "dataclass" in names(node.decorator_list):
                for stmt in node.body:
                    targets = stmt.targets if isinstance(stmt, ast.Assign) else []
                    if any(isinstance(t, ast.Name) and t.id == "DRJIT_STRUCT" for t in targets):
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert not bad, "dataclasses listing their fields again in DRJIT_STRUCT (use @drjit_struct):\n" + "\n".join(bad)
