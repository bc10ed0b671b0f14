"""``report.html``: one self-contained page (no links out): a row per scenario x seed with its
expectations, the changes against the baseline and the run's map image embedded."""
from __future__ import annotations

import base64
import html
import os
from pathlib import Path

from testbed.testing.expect import Outcome, _fmt

IMAGES = ("map.png", "navigate.png")
_CSS = """body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse}td,th{border:1px solid #bbb;
padding:4px 8px;vertical-align:top;font-size:13px}th{background:#eee}.ok{color:#1a7f37}.bad{color:#c0262d;font-weight:bold}
.tol{color:#9a6700}img{width:420px}"""


def _img(out_dir: str) -> str:
    for name in IMAGES:
        p = Path(out_dir) / name
        if p.is_file():
            data = base64.b64encode(p.read_bytes()).decode("ascii")
            return f'<img alt="{html.escape(name)}" src="data:image/png;base64,{data}">'
    return "-"


def _expectations(cell: dict) -> str:
    lines = []
    for o in cell["expectations"]:
        o = Outcome(**o)
        cls = "ok" if o.ok else ("tol" if cell.get("tolerated") else "bad")
        lines.append(f'<div class="{cls}">{"&#10003;" if o.ok else "&#10007;"} {html.escape(o.message())}</div>')
    return "".join(lines) or "-"


def _deltas(cell: dict) -> str:
    lines = []
    for path, d in sorted(cell.get("deltas", {}).items()):
        delta = "no value" if d["delta"] is None else f"{d['delta']:+.4g}"
        cls = "bad" if d["regression"] else "ok"
        lines.append(f'<div class="{cls}">{html.escape(path)}: {delta} (baseline {_fmt(d["baseline"])})</div>')
    return "".join(lines) or "-"


def write_html(path: str | Path, summary: dict) -> None:
    rows = []
    for case in summary["cases"]:
        for cell in case["cells"]:
            verdict = "pass" if cell["passed"] else ("tolerated" if cell.get("tolerated") else
                                                     ("error" if cell["status"] != "ok" else "FAIL"))
            cls = {"pass": "ok", "tolerated": "tol"}.get(verdict, "bad")
            err = f'<div class="bad">{html.escape(str(cell["error"]))}</div>' if cell["error"] else ""
            opts = ", ".join(f"{k}={v}" for k, v in case["options"].items()) or "-"
            rows.append(f'<tr class="cell"><td>{html.escape(case["id"])}</td><td>{cell["seed"]}</td>'
                        f'<td>{html.escape(opts)}</td><td class="{cls}">{verdict}</td>'
                        f'<td>{err}{_expectations(cell)}</td><td>{_deltas(cell)}</td><td>{_img(cell["out_dir"])}</td></tr>')
    cases = "".join(f'<li class="{"ok" if c["passed"] else "bad"}">{html.escape(c["id"])}: '
                    f'{"pass" if c["passed"] else "FAIL"}, {c["pass_rate"]:.0%} of seeds '
                    f'(needs {c["min_pass_rate"]:.0%})</li>' for c in summary["cases"])
    verdict = "PASS" if summary["passed"] else "FAIL"
    page = (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>dopeslam test: {html.escape(summary["name"])}'
            f'</title><style>{_CSS}</style></head><body><h1>dopeslam test: {html.escape(summary["name"])} '
            f'<span class="{"ok" if summary["passed"] else "bad"}">{verdict}</span></h1>'
            f'<p>{len(rows)} runs in {summary.get("wall_seconds", 0):.0f} s</p><ul>{cases}</ul>'
            '<table><thead><tr><th>case</th><th>seed</th><th>options</th><th>result</th><th>expectations</th>'
            f'<th>change against baseline</th><th>map</th></tr></thead><tbody>{"".join(rows)}</tbody></table>'
            '</body></html>')
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
