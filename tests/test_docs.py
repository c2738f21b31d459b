"""The documentation a user copies from: every Python snippet in the docs defines what it uses
(or is an example script, run by tests/test_examples.py), every included example exists with
its markers, and no page or API docstring cites the project's internal history (issue 42, item 9)."""
import ast
import builtins
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md", ROOT / "designs" / "README.md"]
FENCE = re.compile(r"^```(\S*)[^\n]*\n(.*?)^```", re.S | re.M)


def blocks(page: Path, lang: str) -> list[str]:
    return [body for kind, body in FENCE.findall(page.read_text()) if kind == lang]


def undefined_names(code: str, known: set) -> list[str]:
    """Names a snippet reads that nothing before it defines (imports, assignments, loops,
    functions, with-as, comprehensions), in the order they appear."""
    tree = ast.parse(code)
    defined = set(known) | set(dir(builtins))
    missing = []

    class Walk(ast.NodeVisitor):
        def visit_Import(self, node):
            for a in node.names:
                defined.add((a.asname or a.name).split(".")[0])

        visit_ImportFrom = visit_Import

        def visit_FunctionDef(self, node):
            defined.add(node.name)
            defined.update(a.arg for a in node.args.args)
            self.generic_visit(node)

        def visit_Assign(self, node):
            self.visit(node.value)
            for t in node.targets:
                self.visit(t)

        def visit_comprehension(self, node):
            self.visit(node.iter)
            self.visit(node.target)
            for c in node.ifs:
                self.visit(c)

        def visit_ListComp(self, node):
            for g in node.generators:
                self.visit_comprehension(g)
            self.visit(node.elt)

        visit_SetComp = visit_GeneratorExp = visit_ListComp

        def visit_Name(self, node):
            if isinstance(node.ctx, ast.Store):
                defined.add(node.id)
            elif node.id not in defined and node.id not in missing:
                missing.append(node.id)

    Walk().visit(tree)
    known |= defined
    return missing


def test_undefined_names_sees_a_snippet_that_uses_what_it_never_defines():
    assert undefined_names("import numpy as np\nx = np.ones(3)\ny = f(points) + x\n", set()) == ["f", "points"]
    assert undefined_names("[p * 2 for p in range(3)]\nfor k in range(2):\n    k += 1\n", set()) == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_python_snippet_defines_what_it_uses(page):
    known: set = set()  # a page's snippets read top to bottom, as a user pastes them
    for code in blocks(page, "python"):
        assert undefined_names(code, known) == [], f"{page.name}: a snippet uses names it never defines:\n{code}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_included_examples_exist_with_their_markers(page):
    for m in re.finditer(r"```\{literalinclude\} (\S+)\n((?::[a-z-]+:.*\n)*)", page.read_text()):
        src = (page.parent / m.group(1)).resolve()
        assert src.is_file(), f"{page.name}: includes {m.group(1)}, which does not exist"
        code = src.read_text()
        for opt in re.finditer(r":(start-after|end-before): (.*)", m.group(2)):
            assert opt.group(2).strip() in code, f"{page.name}: {src.name} has no line {opt.group(2)!r}"


def test_no_page_or_docstring_cites_internal_history():
    history = re.compile(r"\b(stop|issue) \d+\b")
    found = [f"{p.relative_to(ROOT)}:{n}" for p in PAGES for n, line in enumerate(p.read_text().splitlines(), 1)
             if history.search(line)]
    for pkg in ("single_cilium", "ciliary_carpet"):
        for p in (ROOT / pkg).rglob("*.py"):
            found += [f"{p.relative_to(ROOT)}:{n}" for n, line in enumerate(p.read_text().splitlines(), 1)
                      if history.search(line)]
    assert found == [], "history belongs in benchmarks/results and git, not in what users read: " + ", ".join(found)


def test_the_benchmark_index_names_every_script_and_only_results_files_that_exist():
    readme = (ROOT / "benchmarks" / "README.md").read_text()
    scripts = sorted(p.stem for p in (ROOT / "benchmarks").glob("bench_*.py"))
    missing = [s for s in scripts if f"\n## {s}:" not in readme]
    assert missing == [], f"benchmarks/README.md has no entry for {missing}"
    cited = set(re.findall(r"benchmarks/results/(bench_\w+\.md)", readme)) | set(re.findall(r"`(bench_\w+\.md)`", readme))
    absent = sorted(f for f in cited if not (ROOT / "benchmarks" / "results" / f).is_file() and f != "bench_gpu.md")
    assert absent == [], f"benchmarks/README.md cites results files that do not exist: {absent}"
    assert not re.search(r"\b(stop|issue) \d+\b", readme), "the index holds current results; history goes to the results files"
