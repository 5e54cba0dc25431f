"""What a newcomer reads stays readable: modules of one screenful at a time, guides of one sitting.

Limits of issue 66: no module over 600 lines, no function over 100; every page in docs/ under
500 lines (the decisions log under 400); every measurement table in docs/ names the results
file it comes from.
"""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("render", "selfsup", "benchmarks")


def _modules():
    yield ROOT / "train.py"
    for package in PACKAGES:
        yield from sorted((ROOT / package).rglob("*.py"))


def test_no_module_over_600_lines_and_no_function_over_100():
    long_modules, long_functions = [], []
    for path in _modules():
        text = path.read_text()
        name = path.relative_to(ROOT)
        if text.count("\n") > 600:
            long_modules.append(f"{name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 100:
                    long_functions.append(f"{name}:{node.lineno} {node.name}: {length} lines")
    assert not long_modules and not long_functions, long_modules + long_functions


def test_docs_pages_are_read_in_one_sitting():
    limits = {"decisions.md": 400}
    over = [f"{page.name}: {n}" for page in sorted((ROOT / "docs").glob("*.md"))
            if (n := page.read_text().count("\n")) >= limits.get(page.name, 500)]
    assert not over, over


def test_readme_results_rows_are_one_short_line():
    # A results row is what was measured in a few words and a link; its numbers live in the results file.
    readme = (ROOT / "README.md").read_text().split("## Results", 1)[1].split("\n## ", 1)[0]
    long_rows = [row[:60] for row in readme.split("\n") if row.startswith("|") and len(row) > 240]
    assert not long_rows, long_rows


# Tables that hold no measurement: the data contract's keys and the settings' defaults.
SETTINGS_HEADERS = ("| key |", "| constant |")


def test_every_measurement_table_in_docs_names_its_results_file():
    # The results file is linked in the table or in the paragraph just before it.
    unlinked = []
    for page in sorted((ROOT / "docs").glob("*.md")):
        lines = page.read_text().split("\n")
        i = 0
        while i < len(lines):
            if not lines[i].startswith("|"):
                i += 1
                continue
            end = i
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            start = i
            while start > 0 and not lines[start - 1].strip():
                start -= 1
            while start > 0 and lines[start - 1].strip():  # the paragraph before it
                start -= 1
            if not lines[i].startswith(SETTINGS_HEADERS):
                text = "\n".join(lines[start:end])
                if not re.search(r"benchmarks/results/[\w.\-]+\.(md|json)", text):
                    unlinked.append(f"{page.name}:{i + 1} {lines[i][:60]}")
            i = end
    assert not unlinked, unlinked
