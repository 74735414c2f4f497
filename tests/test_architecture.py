"""The package's import contract (README, "Layout"): tiers import downwards only, kernels stay pure
(arrays in, arrays out: no files, environment, Dask, Zarr, click or YAML), no private names cross
modules, no import cycles.  Read from the source with ``ast``; nothing is imported."""

import ast
import re
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "flakedb"

#: tier of each top-level part of the package (lower number = lower tier)
TIERS = {
    "conventions": 0, "interrupts": 0, "optics": 0, "rt": 0, "colour": 0, "reference": 0, "texture": 0,
    "resources": 1, "atomic": 1, "process": 1, "outputs": 1, "safeio": 1, "paint": 1, "store": 1, "bsdf": 1, "render": 1,
    "appearance": 2, "solve": 3,
    "compose": 4, "pipelines": 4, "match": 4, "export": 4, "cli": 5, "__main__": 5, "__init__": 5,
}
#: libraries (and standard modules) a kernel may not import: I/O, environment, orchestration
KERNEL_FORBIDDEN = {"os", "io", "pathlib", "tempfile", "shutil", "subprocess", "json", "yaml", "h5py", "zarr",
                    "dask", "distributed", "fsspec", "click", "OpenEXR", "PIL", "matplotlib"}
#: libraries only one part of the package may import
ONLY_IN = {"dask": {"pipelines"}, "distributed": {"pipelines"}, "click": {"cli"}, "zarr": {"store"}}


def _modules():
    for p in sorted(PKG.rglob("*.py")):
        rel = p.relative_to(PKG).with_suffix("")
        yield ".".join(("flakedb",) + rel.parts).removesuffix(".__init__"), p


def _part(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(path):
    """(imported module, names, line, at top level) of every import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno, id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.module, [a.name for a in node.names], node.lineno, id(node) in top))
    return out


MODULES = dict(_modules())


def _internal_target(mod, names):
    """The flakedb modules an import statement binds (``from flakedb.x import y`` may name a module)."""
    if not mod.startswith("flakedb"):
        return []
    subs = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in MODULES]
    return subs or [mod]


def test_tiers_import_downwards_only():
    bad = []
    for mod, path in MODULES.items():
        for imp, names, line, _ in _imports(path):
            for target in _internal_target(imp, names):
                if target == "flakedb":
                    if names != ["__version__"]:
                        bad.append(f"{path.name}:{line} imports the package root")
                    continue
                t_src, t_dst = TIERS[_part(mod)], TIERS[_part(target)]
                if t_dst > t_src:
                    bad.append(f"{mod}:{line} (tier {t_src}) imports {target} (tier {t_dst})")
    assert not bad, "\n".join(bad)


def test_kernels_are_pure():
    bad = []
    for mod, path in MODULES.items():
        if TIERS[_part(mod)] != 0:
            continue
        for imp, _, line, _ in _imports(path):
            if imp.split(".")[0] in KERNEL_FORBIDDEN:
                bad.append(f"{mod}:{line} imports {imp}")
        text = path.read_text(encoding="utf-8")
        for word in ("open(", "environ"):
            if word in text.replace("np.open", ""):
                bad.append(f"{mod} uses {word!r}")
    assert not bad, "\n".join(bad)


def test_libraries_stay_in_their_part():
    bad = []
    for mod, path in MODULES.items():
        for imp, _, line, _ in _imports(path):
            allowed = ONLY_IN.get(imp.split(".")[0])
            if allowed is not None and _part(mod) not in allowed:
                bad.append(f"{mod}:{line} imports {imp} (only {sorted(allowed)} may)")
    assert not bad, "\n".join(bad)


def test_no_private_names_cross_modules():
    bad = []
    for mod, path in MODULES.items():
        for imp, names, line, _ in _imports(path):
            if imp.startswith("flakedb"):
                bad += [f"{mod}:{line} imports {imp}.{n}" for n in names if n.startswith("_") and n != "__version__"]
    assert not bad, "\n".join(bad)


def test_internal_imports_at_top_of_file():
    """Only heavy optional libraries may be imported inside functions (with a ``# lazy:`` reason)."""
    bad = []
    for mod, path in MODULES.items():
        lines = path.read_text(encoding="utf-8").split("\n")
        for imp, _, line, at_top in _imports(path):
            if not at_top and (imp.startswith("flakedb") or "# lazy:" not in lines[line - 1] + "".join(lines[line:line + 2])):
                bad.append(f"{mod}:{line} imports {imp} inside a function")
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    graph = {m: set() for m in MODULES}
    for mod, path in MODULES.items():
        for imp, names, _, _ in _imports(path):
            for t in _internal_target(imp, names):
                if t in graph and t != mod:
                    graph[mod].add(t)
    # a package's __init__ re-exporting its own modules is not a cycle of meaning: skip init → child
    for m in graph:
        graph[m] = {t for t in graph[m] if not t.startswith(m + ".")}
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in graph[m]:
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("rule", [test_tiers_import_downwards_only, test_kernels_are_pure])
def test_contract_bites(rule, tmp_path, monkeypatch):
    """The checks fail on a kernel that imports the file format and opens a file."""
    fake = PKG / "rt" / "adding" / "stack.py"
    text = fake.read_text(encoding="utf-8") + "\nimport os\nfrom flakedb.bsdf import table\n"
    p = tmp_path / "stack.py"
    p.write_text(text, encoding="utf-8")
    monkeypatch.setitem(MODULES, "flakedb.rt.adding.stack", p)
    with pytest.raises(AssertionError):
        rule()


def test_cited_documents_are_in_the_repository():
    """Every ``docs/….md`` a module cites exists (docstrings cite documents of this repository)."""
    root = PKG.parent
    missing = set()
    for _, path in MODULES.items():
        for doc in re.findall(r"docs/[\w./-]+?\.md", path.read_text(encoding="utf-8")):
            if not (root / doc).is_file():
                missing.add(f"{path.relative_to(root)} cites {doc}")
    assert not missing, "\n".join(sorted(missing))


def tier_graph():
    """Lines ``part (tier t) → parts it imports`` for every part of the package (README, "Layout")."""
    edges = {}
    for mod, path in MODULES.items():
        src = _part(mod)
        for imp, names, _, _ in _imports(path):
            for t in _internal_target(imp, names):
                dst = _part(t) if t != "flakedb" else None
                if dst and dst != src:
                    edges.setdefault(src, set()).add(dst)
    return [f"{p:12s} (tier {TIERS[p]}) → " + ", ".join(f"{d} ({TIERS[d]})" for d in sorted(edges.get(p, ()), key=lambda d: (TIERS[d], d)))
            for p in sorted(TIERS, key=lambda p: (TIERS[p], p)) if p != "__main__"]


if __name__ == "__main__":  # python -m tests.test_architecture: print the import graph by tier
    print("\n".join(tier_graph()))
