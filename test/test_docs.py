"""The documentation: docs/ builds with Sphinx without a warning, the README stays a short user's
guide whose results table is the one docs/generate.py makes from benchmarks/results, and no
text of the package, the docs or the README names an issue number (say what and why instead)."""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README = REPO / "README.md"
README_MAX_LINES = 300
ISSUE_NUMBER = re.compile(r"[Ii]ssues? #?\d+")
QUICK_START = ("./scripts/demo.sh", "./scripts/test.sh")


def _generate():
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_build_without_warnings(tmp_path):
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    run = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", "-d", str(tmp_path / "doctrees"),
         str(DOCS), str(tmp_path / "html")],
        capture_output=True, text=True, timeout=600, cwd=REPO)
    assert run.returncode == 0, f"sphinx-build failed:\n{run.stdout}\n{run.stderr}"
    html = tmp_path / "html"
    for page in ("index", "getting_started", "reference/generated/cli", "reference/generated/node_parameters",
                 "reference/generated/blocks", "results/index", "decisions/index", "changelog"):
        assert (html / f"{page}.html").is_file(), page
    # the generated reference holds every command, node and block
    cli = (html / "reference/generated/cli.html").read_text()
    for command in ("perception-config train", "perception-config launch", "perception-config bench real",
                    "perception-config episodes export"):
        assert command in cli, command
    parameters = (html / "reference/generated/node_parameters.html").read_text()
    for node in ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node",
                 "bag_replay_node"):
        assert node in parameters, node
    blocks = (html / "reference/generated/blocks.html").read_text()
    for block in ("simulated_init", "icp_point_to_plane", "d2co", "region", "psi_rgb", "simulated_pick"):
        assert block in blocks, block


def test_readme_is_short_and_starts_with_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    for command in QUICK_START:
        assert command in text, command


def test_readme_results_table_is_generated_from_the_results():
    generate = _generate()
    assert generate.readme_table(README) == generate.headline_table(), (
        "README.md's results table differs from benchmarks/results: run `python docs/generate.py readme`")


def test_headline_dates_are_those_its_results_record():
    """The table's measurement dates are the dates its study records carry, and no record is dated
    after the commit that wrote it (where the checkout has that history)."""
    generate = _generate()
    records = generate.headline_records()
    assert records, "no study record in benchmarks/results for the README's table"
    table = generate.headline_table()
    for rec in records.values():
        assert rec["date"] in table
    try:
        shallow = subprocess.run(["git", "rev-parse", "--is-shallow-repository"],
                                 capture_output=True, text=True, cwd=REPO, timeout=60).stdout.strip()
    except OSError:
        pytest.skip("git is not available")
    if shallow == "true":
        pytest.skip("no git history here")
    for name, rec in records.items():
        path = f"benchmarks/results/{name}"
        log = subprocess.run(["git", "log", "-1", "--format=%ad", "--date=short", "--", path],
                             capture_output=True, text=True, cwd=REPO, timeout=60)
        changed = subprocess.run(["git", "status", "--porcelain", "--", path], capture_output=True, text=True,
                                 cwd=REPO, timeout=60).stdout.strip()
        if log.returncode == 0 and log.stdout.strip() and not changed:
            assert rec["date"] <= log.stdout.strip(), f"{path} is dated after the commit that wrote it"


def _text_files():
    yield README
    for folder, suffixes in ((REPO / "perception_config", {".py", ".yaml", ".xml", ".md"}),
                             (DOCS, {".md", ".py", ".rst"})):
        for path in sorted(folder.rglob("*")):
            if path.suffix in suffixes and "_build" not in path.parts and "generated" not in path.parts:
                yield path


def test_no_issue_numbers_in_package_docs_and_readme():
    found = []
    for path in _text_files():
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if ISSUE_NUMBER.search(line):
                found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()}")
    assert not found, "issue numbers (say what and why instead):\n" + "\n".join(found)
