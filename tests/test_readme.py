"""The README's commands and example stay true."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_readme_starts_with_the_two_setup_commands_and_ci_runs_the_test_one():
    first_block = re.search(r"```bash\n(.*?)```", README, re.S).group(1).strip().splitlines()
    assert len(first_block) == 2
    assert first_block[0].endswith("python train.py")
    assert "pytest" in first_block[1]
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1] == first_block[1]


def test_readme_examples_run():
    blocks = re.findall(r"```python\n(.*?)```", README, re.S)
    assert len(blocks) >= 2  # the estimator's and the layer's
    for code in blocks:
        exec(compile(code, "README.md", "exec"), {})


def test_readme_links_reach_their_sections_and_files():
    # GitHub's heading anchors: lower case, punctuation dropped, spaces as hyphens.
    anchors = {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
               for heading in re.findall(r"^#+ (.*)$", README, re.M)}
    targets = re.findall(r"\]\(([^)\s]+)\)", README)
    assert targets
    for target in targets:
        if target.startswith("#"):
            assert target[1:] in anchors, f"README links to a missing section {target}"
        elif "://" not in target:
            assert (ROOT / target.split("#")[0]).exists(), f"README links to a missing file {target}"


def test_docs_links_reach_their_files_and_sections():
    def anchors(path: Path) -> set[str]:
        return {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
                for heading in re.findall(r"^#+ (.*)$", path.read_text(), re.M)}

    for doc in sorted((ROOT / "docs").glob("*.md")):
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if "://" in target:
                continue
            path, _, anchor = target.partition("#")
            file = (doc.parent / path).resolve() if path else doc
            assert file.exists(), f"{doc.name} links to a missing file {target}"
            if anchor and file.suffix == ".md":
                assert anchor in anchors(file), f"{doc.name} links to a missing section {target}"
