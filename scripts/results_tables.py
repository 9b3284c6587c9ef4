"""Render the results tables of the README and docs/results.md from results/records.json.

    python scripts/results_tables.py            # rewrite the tables in place
    python scripts/results_tables.py --check    # exit 1, naming the file, where one differs

A table sits between ``<!-- results-table: NAME -->`` and ``<!-- /results-table -->``; the
records are the only place a figure is written by hand (a new result: a new record).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "results" / "records.json"
DOCUMENTS = (ROOT / "README.md", ROOT / "docs" / "results.md")
TABLE = re.compile(r"(<!-- results-table: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /results-table -->)",
                   re.DOTALL)
#: The paper's Table I order, then its manipulation tasks.
TASKS = ("cartpole-balance", "cup-catch", "cheetah-run", "hopper-stand", "walker-walk",
         "finger-turn_easy", "panda-push", "panda-lift")
CAPTION = ("Bold: a `readout` student at ≥ 0.9 of its teacher's return (Panda: ≥ 0.8 of its "
           "success rate); a task without a row of ours has none yet.")
#: The targets a student's ratio is bold at: its return over its teacher's (Panda: success).
TARGET, SUCCESS_TARGET = 0.9, 0.8


def load(path: Path = RECORDS) -> list[dict[str, Any]]:
    """The records, refused where two share an id or one names an unknown task."""
    records = json.loads(path.read_text())
    ids = [r["id"] for r in records]
    if len(set(ids)) != len(ids):
        raise SystemExit(f"{path}: record ids repeat: {sorted({i for i in ids if ids.count(i) > 1})}")
    cells: dict[tuple[str, str, str], str] = {}
    for record in records:
        if record["task"] not in TASKS:
            raise SystemExit(f"{path}: record {record['id']} names unknown task {record['task']!r}")
        cell = (record["task"], record["setting"], record["agent"])
        if cell in cells:
            raise SystemExit(f"{path}: records {cells[cell]} and {record['id']} fill one cell, "
                             f"{cell}")
        cells[cell] = record["id"]
    return records


def figure(record: dict[str, Any] | None, paper_prefix: bool = False) -> str:
    """One cell: the mean, the 30-episode mean or the success rate in brackets, a note."""
    if record is None:
        return ""
    text = f"{record['mean']:.1f}"
    if record.get("mean_30") is not None:
        text += f" ({record['mean_30']:.1f})"
    elif record.get("success") is not None:
        text += f" ({record['success']:.2f})"
    elif record.get("ratio_to_teacher") is not None and record["agent"] != "readout":
        text += f" ({record['ratio_to_teacher']:.2f})"
    if record.get("note"):
        text += f" ({record['note']})"
    if paper_prefix and record["agent"] == "paper-recipe":
        text = f"TWIST {text}"
    return text


def ratio(record: dict[str, Any] | None) -> str:
    """The readout student's ratio to its teacher, 30-episode or success ratio in brackets."""
    if record is None or record.get("ratio_to_teacher") is None:
        return ""
    text = f"{record['ratio_to_teacher']:.2f}"
    for key in ("ratio_to_teacher_30", "ratio_success"):
        if record.get(key) is not None:
            text += f" ({record[key]:.2f})"
    return text


def meets_target(record: dict[str, Any]) -> bool:
    if record.get("ratio_success") is not None:
        return record["ratio_success"] >= SUCCESS_TARGET
    return record.get("ratio_to_teacher") is not None and record["ratio_to_teacher"] >= TARGET


def student_cells(readout: dict[str, Any] | None) -> tuple[str, str]:
    """The `readout` student's figure and ratio cells, bold where it meets its target."""
    student, share = figure(readout), ratio(readout)
    if readout is not None and meets_target(readout):
        return f"**{student}**", f"**{share}**"
    return student, share


def rows(records: Iterable[dict[str, Any]]) -> list[tuple[str, str, dict[str, dict[str, Any]]]]:
    """(task, setting, {agent: record}) in the records' order, one per task and setting."""
    out: dict[tuple[str, str], dict[str, dict[str, Any]]] = {}
    for record in records:
        out.setdefault((record["task"], record["setting"]), {})[record["agent"]] = record
    return [(task, setting, cells) for (task, setting), cells in out.items()]


def overview(records: list[dict[str, Any]]) -> str:
    """Every row: ours, then the paper's beside them."""
    lines = [CAPTION, "", "| task, `quick` | teacher on states | `readout` student | / teacher "
             "| `paper` recipe | Dreamer w/ DR | zero actions |", "|---|---|---|---|---|---|---|"]
    for task, setting, cells in rows(records):
        readout = cells.get("readout")
        student, share = student_cells(readout)
        paper = any(r["source"] == "paper" for r in cells.values())
        lines.append(f"| {task}, {setting} | {figure(cells.get('teacher'))} | {student} | {share} | "
                     f"{figure(cells.get('paper-recipe'), paper)} | "
                     f"{figure(cells.get('dreamer-dr'))} | {figure(cells.get('zero'))} |")
    return "\n".join(lines) + "\n"


def readme(records: list[dict[str, Any]]) -> str:
    """One row per task of the paper (its first row of ours, dashes where there is none), the
    paper's figures in a column of their own; a row's setting beyond its seeds and episodes in
    a note below the table, so that every line stays short."""
    lines = ["| task | seeds | episodes | teacher on states | `readout` student | / teacher "
             "| `paper` recipe | Dreamer w/ DR | zero | the paper: oracle / TWIST / Dreamer w/ DR |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    first: dict[str, tuple[str, dict[str, dict[str, Any]]]] = {}
    for task, setting, cells in rows(r for r in records if r["source"] == "ours"):
        first.setdefault(task, (setting, cells))
    paper: dict[str, dict[str, dict[str, Any]]] = {}
    for record in records:
        if record["source"] == "paper":
            paper.setdefault(record["task"], {})[record["agent"]] = record
    notes = []
    for task in TASKS:
        theirs = paper.get(task, {})
        published = " / ".join(f"{theirs[a]['mean']:.1f}" if a in theirs else "–"
                               for a in ("teacher", "paper-recipe", "dreamer-dr")) if theirs else ""
        if task not in first:
            lines.append(f"| {task} | – | – | – | – | – | – | – | – | {published} |")
            continue
        setting, cells = first[task]
        readout = cells.get("readout")
        student, share = student_cells(readout)
        lead = cells.get("teacher") or next(iter(cells.values()))
        seeds = ", ".join(str(s) for s in lead["collection_seeds"])
        episodes = str(lead["episodes"])
        if any(r.get("mean_30") is not None for r in cells.values()):
            episodes += " (30)"
        lines.append(f"| {task} | {seeds} | {episodes} | {figure(cells.get('teacher'))} | "
                     f"{student} | {share} | {figure(cells.get('paper-recipe'))} | "
                     f"{figure(cells.get('dreamer-dr'))} | {figure(cells.get('zero'))} | "
                     f"{published} |")
        detail = re.search(r"\((.*)\)\s*$", setting)
        if detail and detail[1] != "success":  # success rates are the caption's
            notes.append(f"- {task}: {detail[1]}.")
    return "\n".join([*lines, *([""] if notes else []), *notes]) + "\n"


RENDERERS = {"overview": overview, "readme": readme}


def rendered(text: str, records: list[dict[str, Any]]) -> str:
    """``text`` with every marked table rendered from ``records``."""
    def table(match: re.Match[str]) -> str:
        name = match["name"]
        if name not in RENDERERS:
            raise SystemExit(f"unknown results table {name!r}; known: {', '.join(RENDERERS)}")
        return match.group(1) + RENDERERS[name](records) + match.group(4)

    return TABLE.sub(table, text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="change nothing; exit 1 where a table differs from the records")
    args = parser.parse_args(argv)
    records = load()
    stale = []
    for path in DOCUMENTS:
        text = path.read_text()
        new = rendered(text, records)
        if new != text:
            stale.append(path)
            if not args.check:
                path.write_text(new)
    for path in stale:
        print(f"{path.relative_to(ROOT)}: {'differs from' if args.check else 'rendered from'} "
              f"{RECORDS.relative_to(ROOT)}", file=sys.stderr if args.check else sys.stdout)
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
