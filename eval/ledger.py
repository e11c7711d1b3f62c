"""The model ledger of the discovery loop: one JSON line per fit (``model_ledger.jsonl``), read back as a table and
a plot of the held-out error per model version beside what its corrected frames achieve."""

from __future__ import annotations

import json
from pathlib import Path

from watergan.errors import UserInputError

LEDGER_NAME = "model_ledger.jsonl"


def append_ledger(folder: Path, record: dict) -> None:
    """Append one JSON line to ``folder/model_ledger.jsonl``."""
    with open(folder / LEDGER_NAME, "a") as f:
        f.write(json.dumps(record) + "\n")


def find_ledger(target: str | Path) -> Path:
    """The ledger of a workspace (or of a bare survey's diagnose/ folder)."""
    root = Path(target)
    for path in (root / LEDGER_NAME, root / "diagnose" / LEDGER_NAME):
        if path.is_file():
            return path
    raise UserInputError(f"no {LEDGER_NAME} in {root}: run `watergan diagnose {root}` first")


def read_ledger(path: Path) -> list[dict]:
    """Every record of a ledger file."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def ledger_table(records: list[dict]) -> str:
    """A plain-text table: version, time, kind, held-out RMSE, change from the previous model, stack;
    then, for records that carry them, the consistency and board error of the corrected frames."""
    lines = [f"{'ver':>3}  {'time':19}  {'kind':9}  {'heldout_rmse':>12}  {'change':>7}  stack"]
    previous = None
    for i, r in enumerate(records):
        change = "" if previous is None or r["kind"] != "model" else f"{(r['heldout_rmse'] / previous - 1) * 100:+.1f}%"
        lines.append(f"{i:>3}  {r['time']:19}  {r['kind']:9}  {r['heldout_rmse']:12.5f}  {change:>7}  "
                     f"{','.join(r['stack'])}")
        if r["kind"] == "model":
            previous = r["heldout_rmse"]
    colour = [(i, r) for i, r in enumerate(records) if r.get("consistency") or r.get("board_ciede2000")]
    if colour:
        lines.append("\ncolour of the corrected frames when the version was fitted (the eval stage's, and folders "
                     "`watergan consistency` measured): consistency = mean variance of c/(R+G+B) across views "
                     "(lower = more consistent), board = mean CIEDE2000 to the true patch colours")
        for i, r in colour:
            for name in sorted({*r.get("consistency", {}), *r.get("board_ciede2000", {})}):
                var = r.get("consistency", {}).get(name)
                de = r.get("board_ciede2000", {}).get(name)
                lines.append(f"{i:>3}  {name:24}  consistency {'-' if var is None else f'{var:.3e}':>9}  "
                             f"board {'-' if de is None else f'{de:.2f}':>6}")
    return "\n".join(lines)


def plot_ledger(records: list[dict], path: Path) -> None:
    """Held-out RMSE per ledger entry: model versions joined by a line, candidate trials as dots; beside it,
    when model versions carry them, what their corrected frames achieve (the board's CIEDE2000 and the colour
    consistency per image folder, one line each), so adding an effect can be seen to lower the error of the
    frames users texture with."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colour_keys = [k for k in ("board_ciede2000", "consistency") if any(r.get(k) for r in records)]
    fig, axes = plt.subplots(1, 1 + len(colour_keys), figsize=(7 + 4.5 * len(colour_keys), 3.6), squeeze=False)
    ax = axes[0, 0]
    model = [(i, r["heldout_rmse"]) for i, r in enumerate(records) if r["kind"] == "model"]
    trials = [(i, r["heldout_rmse"]) for i, r in enumerate(records) if r["kind"] != "model"]
    if trials:
        ax.scatter(*zip(*trials, strict=True), s=12, color="0.6", label="candidate trial")
    if model:
        ax.plot(*zip(*model, strict=True), "o-", color="tab:blue", label="model version")
        for i, r in enumerate(records):
            if r["kind"] == "model":
                ax.annotate("+".join(r["stack"][-1:]), (i, r["heldout_rmse"]), fontsize=7,
                            textcoords="offset points", xytext=(3, 4))
    ax.set_xlabel("ledger entry")
    ax.set_ylabel("held-out RMSE (linear)")
    ax.legend(fontsize=8)
    for ax, key in zip(axes[0, 1:], colour_keys, strict=True):
        names = sorted({n for r in records for n in (r.get(key) or {})})
        for name in names:
            points = [(i, r[key][name]) for i, r in enumerate(records) if name in (r.get(key) or {})]
            ax.plot(*zip(*points, strict=True), "o-", label=name)
        ax.set_xlabel("ledger entry")
        ax.set_ylabel("board CIEDE2000" if key == "board_ciede2000" else "consistency (variance of c/(R+G+B))")
        ax.set_title("corrected frames per model version", fontsize=9)
        ax.set_yscale("log")  # raw frames sit one to two decades above the corrections
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
