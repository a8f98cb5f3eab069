"""docs/reliability.md from a fault-matrix run: one table row per tests/faults JSON result.

    COMPD_FAULTS_OUT=build/faults pytest tests/faults
    python -m compd.commissioning.faultdoc build/faults --doc docs/reliability.md

Only the block between the `faults` markers is rewritten; the rest of the page is prose.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

COLUMNS = (
    "row",
    "fault",
    "transport",
    "policy",
    "expected behaviour",
    "largest step µm (allowed/cycle)",
    "time to safe state s",
    "samples lost",
    "event logged",
    "word: step LSB, pace, off by µm (band)",
    "word valid",
)


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin (generated, do not edit) -->", f"<!-- {name}:end -->"


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def render_matrix(results: Sequence[dict[str, Any]]) -> str:
    """The markdown table, in matrix order (`order`, then row id)."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in sorted(results, key=lambda r: (r.get("order", 1000), r["row"])):
        safe = r.get("time_to_safe_s")
        ok = (
            r.get("word_valid")
            and r.get("max_step_ratio", 0.0) <= 1.01
            and r.get("word_max_step_lsb", 0) <= 1
            and r.get("word_pace_ratio", 0.0) <= 1.0 + 1e-6
            and r.get("word_max_error_um", 0.0) <= r.get("word_band_um", 0.0) + 1e-9
        )
        cells = [
            f"`{r['row']}`",
            r["fault"],
            r["transport"],
            r["policy"],
            r["expected"],
            f"{r['max_step_um']:.3f} ({r['allowed_step_um']:.3f})",
            "n/a" if safe is None else f"{safe:.3f}",
            str(r["samples_lost"]),
            (r.get("event") or "—") + ("" if r.get("logged") else " (not in the log)"),
            "—"
            if not r.get("word_band_um")
            # a row that does not see the word
            else (
                f"{r['word_max_step_lsb']}, {r['word_pace_ratio']:.2f},"
                f" {r['word_max_error_um']:.2f} ({r['word_band_um']:.2f})"
            ),
            "yes" if ok else "NO",
        ]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines)


def replace_block(text: str, name: str, block: str) -> str:
    """`text` with what lies between the `name` markers replaced (markers appended if absent)."""
    begin, end = markers(name)
    body = f"{begin}\n{block}\n{end}"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        return head + body + tail
    return text.rstrip("\n") + "\n\n" + body + "\n"


def read_block(text: str, name: str) -> str | None:
    begin, end = markers(name)
    if begin not in text or end not in text:
        return None
    return text.split(begin, 1)[1].split(end, 1)[0]


def table_rows(block: str) -> tuple[list[str], list[list[str]]]:
    """(header cells, body rows as cells) of the first markdown table in `block`."""
    rows = [ln.strip() for ln in block.splitlines() if ln.strip().startswith("|")]
    split = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in rows]
    if not split:
        return [], []
    return split[0], split[2:]


def load_results(folder: Path) -> list[dict[str, Any]]:
    return [json.loads(p.read_text(encoding="utf-8")) for p in sorted(folder.glob("*.json"))]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m compd.commissioning.faultdoc", description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="folder of the rows' JSON files")
    ap.add_argument("--doc", type=Path, default=Path("docs/reliability.md"))
    args = ap.parse_args(argv)
    results = load_results(args.results)
    if not results:
        print(f"faultdoc: no results in {args.results}", file=sys.stderr)
        return 2
    text = args.doc.read_text(encoding="utf-8") if args.doc.exists() else "# Reliability\n"
    args.doc.write_text(replace_block(text, "faults", render_matrix(results)), encoding="utf-8")
    print(f"{args.doc}: {len(results)} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
