"""The README's headline table and its Status's claims, written from a results JSON of `bench_product.py`.

    .venv/bin/python benchmarks/readme_table.py [--check] [--result benchmarks/results/product_fast.json]

The JSON is re-measured (about ten minutes on two cores) by

    .venv/bin/python benchmarks/bench_product.py --out DIR --cases clean,mono --runs 1 \\
        --result benchmarks/results/product_fast.json

The table's columns are the ``clean`` case's first run (raw, every baseline, the restorer with range, the physics
correction, the oracle) and the ``mono`` case's restorer; its rows are the figures the JSON holds: the board's mean
CIEDE2000 and distance, the consistency (variance of normalised colour across each point's views) x1e-5 per
channel, and the PSNR against the in-air truth. Each value is written with three significant figures. The Status's
claims are computed from the table as written (:func:`status_claims`): each correction's board error as a multiple
of the oracle's, whether it is below every baseline's, and in which channels its consistency is lower than raw's and
every baseline's.

README.md holds the generated text between ``<!-- table:begin -->`` and ``<!-- table:end -->`` (the paragraph that
names the commit, and the table) and between ``<!-- claims:begin -->`` and ``<!-- claims:end -->`` (the Status's
bullets). Without ``--check`` the README is rewritten there; with it nothing is written and the exit status is 1 when
the README differs from what the JSON gives.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULT = ROOT / "benchmarks" / "results" / "product_fast.json"
WIDTH = 116
"""The README's line width."""

#: (column label, bench_product case, method key in that case's figures, restorer mode the case must have run)
COLUMNS = (
    ("raw", "clean", "raw", "rgb-d"),
    ("hist. eq.", "clean", "histeq", "rgb-d"),
    ("CLAHE", "clean", "clahe", "rgb-d"),
    ("gray world", "clean", "gray_world", "rgb-d"),
    ("Jaffe-McGlamery", "clean", "jaffe", "rgb-d"),
    ("Sea-thru", "clean", "seathru", "rgb-d"),
    ("ours, RGB-D", "clean", "ours", "rgb-d"),
    ("ours, monocular", "mono", "ours", "monocular"),
    ("physics (range)", "clean", "physics", "rgb-d"),
    ("oracle", "clean", "oracle", "rgb-d"),
)
#: (row label, key of a run's record, channel index or None, scale)
ROWS = (
    ("board, CIEDE2000", "board_ciede2000", None, 1.0),
    ("board, distance", "board_distance", None, 1.0),
    ("consistency R", "consistency", 0, 1e5),
    ("consistency G", "consistency", 1, 1e5),
    ("consistency B", "consistency", 2, 1e5),
    ("PSNR (dB)", "psnr_db", None, 1.0),
)
#: How the Status names each correction's column.
CORRECTIONS = {
    "ours, RGB-D": "**Restorer, RGB-D** (frames with stereo or MVS range)",
    "ours, monocular": "**Restorer, monocular** (frames without range)",
    "physics (range)": "**Physics correction** (the water inverted at each pixel's range)",
}
#: What each recorded figure is, for the paragraph above the table (in the order of ROWS).
MEANINGS = {
    "board_ciede2000": "board: the colour board's mean CIEDE2000",
    "board_distance": "board distance: its mean distance of normalised RGB",
    "consistency": "consistency: variance of normalised colour across each 3D point's views, x1e-5 (lower is "
                   "better; a constant image scores 0, so read it beside the board)",
    "psnr_db": "PSNR against the in-air truth",
}
INTRO = ("`watergan run` on the simulated demo survey with nothing hidden (44 stereo frames of 640x480), measured at "
         "commit {commit} (`benchmarks/results/{json}`). {meanings}. \"ours\" is the restorer with range (RGB-D) or "
         "without (monocular: a flat seafloor at the navigation's altitude, with the site depth net's relief where "
         "that wins on held-out frames); \"oracle\" inverts the true water with the true range.")


def cell(value: float) -> str:
    """Three significant figures, without an exponent."""
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.3g}"


def table_rows(result: dict) -> list[tuple[str, list[str]]]:
    """The table's rows (label, one cell per column) from a bench_product result; a figure that some column's run
    did not record leaves its row out."""
    runs = {}
    for label, case, _, mode in COLUMNS:
        if not result["runs"].get(case):
            raise SystemExit(f"the result has no {case!r} run, which the column {label!r} needs")
        run = result["runs"][case][0]
        if run["restorer_mode"] != mode:
            raise SystemExit(f"the {case!r} run corrected in {run['restorer_mode']} mode, not {mode}")
        runs[case] = run
    rows = []
    for label, key, channel, scale in ROWS:
        if not all(method in runs[case].get(key, {}) for _, case, method, _ in COLUMNS):
            continue
        values = [runs[case][key][method] for _, case, method, _ in COLUMNS]
        rows.append((label, [cell(scale * (v if channel is None else v[channel])) for v in values]))
    return rows


def table_markdown(result: dict, json_name: str) -> str:
    """The paragraph naming the commit, and the table."""
    if "commit" not in result:
        raise SystemExit("the result names no commit: re-measure it with bench_product.py")
    header = "| | " + " | ".join(label for label, *_ in COLUMNS) + " |"
    lines = [header, "|---" * (len(COLUMNS) + 1) + "|"]
    rows = table_rows(result)
    lines += [f"| {label} | " + " | ".join(cells) + " |" for label, cells in rows]
    keys = {key for label, key, *_ in ROWS if label in dict(rows)}
    meanings = "; ".join(text for key, text in MEANINGS.items() if key in keys)
    intro = INTRO.format(commit=result["commit"], json=json_name, meanings=meanings[0].upper() + meanings[1:])
    return textwrap.fill(intro, WIDTH, break_long_words=False, break_on_hyphens=False) + "\n\n" + "\n".join(lines)


def parse_table(text: str) -> dict[str, dict[str, float]]:
    """A markdown table's rows as {row label: {column label: value}}."""
    cells = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
             if line.startswith("|")]
    header, rows = cells[0], cells[2:]
    return {row[0]: {col: float(value) for col, value in zip(header[1:], row[1:], strict=True)} for row in rows}


def channels(ok: list[bool]) -> str:
    """'in every channel', 'in no channel' or 'in red and green, not in blue'."""
    names = [n for n, good in zip(("red", "green", "blue"), ok, strict=True) if good]
    bad = [n for n, good in zip(("red", "green", "blue"), ok, strict=True) if not good]
    if not bad:
        return "in every channel"
    if not names:
        return "in no channel"
    return f"in {' and '.join(names)}, not in {' and '.join(bad)}"


def claims_by_column(table: dict[str, dict[str, float]]) -> dict[str, list[str]]:
    """Per correction's column, the phrases the Status states: its board CIEDE2000 and that as a multiple of the
    oracle's; for the restorer's columns also whether its board error is below every baseline's, and in which
    channels its consistency is lower than raw's (and every baseline's, where that holds in the same channels)."""
    board = table["board, CIEDE2000"]
    ours = [c for c in board if c.startswith("ours")]
    baselines = [c for c in board if c not in ours and c not in ("physics (range)", "oracle")]
    out = {}
    for col in ours + ["physics (range)"]:
        out[col] = [f"{board[col]:g}, {board[col] / board['oracle']:.2f}x the oracle's"]
    for col in ours:
        below = all(board[col] < board[b] for b in baselines)
        out[col].append("board error below every baseline's" if below else "board error not below every baseline's")
        consistency = [table[f"consistency {c}"] for c in "RGB"]
        vs_raw = [row[col] < row["raw"] for row in consistency]
        vs_all = [all(row[col] < row[b] for b in baselines) for row in consistency]
        if vs_all == vs_raw and any(vs_raw):
            out[col].append(f"consistency lower than raw's and every baseline's {channels(vs_raw)}")
        else:
            out[col].append(f"consistency lower than raw's {channels(vs_raw)}")
    return out


def status_claims(table: dict[str, dict[str, float]]) -> tuple[list[str], set[str]]:
    """Every phrase the Status must contain, computed from the table, and the ratios it may quote."""
    by_column = claims_by_column(table)
    board = table["board, CIEDE2000"]
    ratios = {f"{board[col] / board['oracle']:.2f}x" for col in by_column}
    return [claim for claims in by_column.values() for claim in claims], ratios


def claims_markdown(table: dict[str, dict[str, float]]) -> str:
    """The Status's bullets: one per correction, its claims in order."""
    return "\n".join(textwrap.fill(f"- {CORRECTIONS[col]}: board CIEDE2000 {'; '.join(claims)}.", WIDTH,
                                   subsequent_indent="  ", break_long_words=False, break_on_hyphens=False)
                     for col, claims in claims_by_column(table).items())


def between(text: str, name: str) -> tuple[int, int]:
    """The span of ``text`` between ``<!-- name:begin -->`` and ``<!-- name:end -->`` (both on lines of their own)."""
    match = re.search(rf"^<!-- {name}:begin -->\n(.*?)^<!-- {name}:end -->$", text, flags=re.S | re.M)
    if match is None:
        raise SystemExit(f"README has no <!-- {name}:begin --> ... <!-- {name}:end --> block")
    return match.start(1), match.end(1)


def render(readme: str, result: dict, json_name: str = RESULT.name) -> str:
    """``readme`` with its table and claims blocks written from ``result``."""
    table = table_markdown(result, json_name)
    start, end = between(readme, "table")
    readme = readme[:start] + table + "\n" + readme[end:]
    claims = claims_markdown(parse_table(table))
    start, end = between(readme, "claims")
    return readme[:start] + claims + "\n" + readme[end:]


def differences(readme_path: Path = README, result_path: Path = RESULT) -> list[str]:
    """The unified diff from the README as it is to the README the result gives (empty: they agree)."""
    readme = readme_path.read_text()
    wanted = render(readme, json.loads(result_path.read_text()), result_path.name)
    return list(difflib.unified_diff(readme.splitlines(), wanted.splitlines(), "README.md", "from " + result_path.name,
                                     lineterm=""))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when README.md differs; write nothing")
    parser.add_argument("--result", type=Path, default=RESULT, help="the bench_product.py JSON")
    parser.add_argument("--readme", type=Path, default=README)
    args = parser.parse_args()
    diff = differences(args.readme, args.result)
    if args.check:
        print("\n".join(diff) if diff else f"{args.readme.name} agrees with {args.result.name}")
        return 1 if diff else 0
    if diff:
        args.readme.write_text(render(args.readme.read_text(), json.loads(args.result.read_text()), args.result.name))
    print(f"{args.readme.name}: {'rewritten' if diff else 'unchanged'} from {args.result.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
