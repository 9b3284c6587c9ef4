"""The documents a newcomer reads: links that resolve, a short front page, and text about the
product rather than about how it was built."""

import functools
import json
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = [ROOT / "README.md", ROOT / "datasets.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "research").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
#: A spelled-out ordinal, recognised by its ending ("...th", "...st", ...) or written in digits.
ORDINAL = r"(?:(?:[a-z]+-)?[a-z]+(?:st|nd|rd|th)|\d+(?:st|nd|rd|th))"
#: Endings that only ordinals from four upwards have (so "(depth)" or "(both)" do not count).
ORDINAL_ENDING = r"(?:[a-z]+-)?[a-z]+(?:teenth|tieth|enth|inth|fth|xth|hth|urth)"
HISTORY = re.compile(rf"(?i)\b{ORDINAL}\s+(?:session|work\s+period)s?\b|\bissue\s+#?\d+|"
                     r"\bwork\s+periods?\b|\bthis\s+release\b")
#: In prose, a bare ordinal in brackets names a work period too.
BRACKETED = re.compile(rf"(?i)\({ORDINAL_ENDING}\b[^)]*\)")


def slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


@functools.cache
def anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return {slug(m) for m in re.findall(r"(?m)^#+ (.+)$", text)}


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: p.name)
def test_relative_links_resolve(document: Path) -> None:
    text = re.sub(r"```.*?```", "", document.read_text(), flags=re.S)
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (document.parent / path).resolve() if path else document
        missing_anchor = bool(anchor) and file.suffix == ".md" and (
            not file.exists() or anchor not in anchors(file))
        if not file.exists() or missing_anchor:
            broken.append(target)
    assert not broken, f"{document.name}: links to nothing: {broken}"


def test_front_page_is_short() -> None:
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


@pytest.mark.parametrize(("page", "most"), [("docs/results.md", 250), ("docs/findings.md", 200)])
def test_the_pages_a_user_reads_stay_short(page: str, most: int) -> None:
    """How a figure was found belongs in research/; these pages keep the figures and commands."""
    lines = (ROOT / page).read_text().splitlines()
    assert len(lines) <= most, f"{page} has {len(lines)} lines; move narrative to research/"
    long = [i + 1 for i, line in enumerate(lines) if len(line) > 200 and not line.startswith("|")]
    assert not long, f"{page}: lines {long} are over 200 characters"


@pytest.mark.parametrize("page", [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda page: page.name)
def test_no_line_of_the_docs_is_over_200_characters(page: Path) -> None:
    """Table rows included: a row too wide to read is a row whose detail belongs below it."""
    long = [i + 1 for i, line in enumerate(page.read_text().splitlines()) if len(line) > 200]
    assert not long, f"{page.name}: lines {long} are over 200 characters"


def test_no_development_history_in_tracked_files() -> None:
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    found = []
    for name in listed.stdout.splitlines():
        path = ROOT / name
        if path.suffix not in {".py", ".md", ".sh", ".toml", ".txt", ".yaml", ".yml", ""}:
            continue
        if not path.is_file() or path == Path(__file__).resolve():
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line) or (path.suffix == ".md" and BRACKETED.search(line)):
                found.append(f"{name}:{number}: {line.strip()[:80]}")
    assert not found, "development history in the project:\n" + "\n".join(found[:20])


def _tables():
    import importlib.util

    spec = importlib.util.spec_from_file_location("results_tables",
                                                  ROOT / "scripts" / "results_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_results_tables_are_rendered_from_the_records() -> None:
    tables = _tables()
    records = tables.load()
    for path in tables.DOCUMENTS:
        text = path.read_text()
        assert tables.TABLE.search(text), f"{path.name} holds no rendered results table"
        assert tables.rendered(text, records) == text, (
            f"{path.name}'s results table differs from results/records.json: "
            "python scripts/results_tables.py renders it")
    # A figure changed in a record changes the table (the check could fail).
    changed = [dict(r, mean=r["mean"] + 1.0) if r["id"] == records[0]["id"] else r
               for r in records]
    readme = (ROOT / "README.md").read_text()
    assert tables.rendered(readme, changed) != readme
    assert f"{records[0]['mean'] + 1.0:.1f}" in tables.readme(changed)


def test_every_record_names_what_a_figure_needs(tmp_path: Path) -> None:
    tables = _tables()
    for record in tables.load():
        assert record["source"] in ("ours", "paper"), record["id"]
        assert isinstance(record["mean"], int | float), record["id"]
        if record["source"] == "ours":
            assert record["section"] and record["episodes"], record["id"]
    copy = tmp_path / "records.json"
    copy.write_text((ROOT / "results" / "records.json").read_text().replace(
        '"id": "cartpole-3seeds-readout"', '"id": "cartpole-3seeds-teacher"'))
    with pytest.raises(SystemExit, match="repeat"):
        tables.load(copy)
    twice = [r for r in tables.load() if r["id"] == "cartpole-3seeds-readout"]
    copy.write_text(json.dumps([*tables.load(), dict(twice[0], id="another")]))
    with pytest.raises(SystemExit, match="fill one cell"):
        tables.load(copy)
