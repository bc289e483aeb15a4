"""The review page: the paper's human sampling of annotations, as one static HTML file.

A reviewer sees N sampled trajectories (grid, six QA pairs, metadata), marks each accept
or reject, and exports {"marks": {trajectory: "accept"|"reject"}} as JSON; rebuilding
with `review=marks.json` leaves the rejected trajectories out. Every piece of text is
HTML-escaped server-side; the script only reads data-* attributes, never inserts HTML.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from labrobfail_vlm.io import atomic_write_bytes

if TYPE_CHECKING:
    from labrobfail_data.annotate import Annotated

_E = html.escape

_SCRIPT = """
const marks = {};
function mark(btn) {
  const card = btn.closest('.card');
  marks[card.dataset.trajectory] = btn.dataset.mark;
  card.dataset.state = btn.dataset.mark;
  card.querySelector('.state').textContent = btn.dataset.mark;
  render();
}
function render() {
  const text = JSON.stringify({marks: marks}, null, 1);
  document.getElementById('marks-json').value = text;
  document.getElementById('count').textContent = Object.keys(marks).length;
  return text;
}
function exportMarks() {
  const blob = new Blob([render()], {type: 'application/json'});
  const a = document.getElementById('download');
  a.href = URL.createObjectURL(blob);
  a.download = 'review_marks.json';
  a.click();
}
document.querySelectorAll('button[data-mark]').forEach(b => b.addEventListener('click', () => mark(b)));
document.getElementById('export').addEventListener('click', exportMarks);
render();
"""

_STYLE = """
body{font-family:sans-serif;margin:1em;background:#fafafa} .card{background:#fff;border:2px solid #ccc;
margin:1em 0;padding:.8em;border-radius:6px} .card[data-state=accept]{border-color:#2a9d8f}
.card[data-state=reject]{border-color:#e76f51} img{max-width:100%;height:auto} table{border-collapse:collapse}
td{border-top:1px solid #eee;padding:3px 8px;vertical-align:top} .q{white-space:pre-wrap;color:#333}
.a{font-weight:bold} #bar{position:sticky;top:0;background:#fafafa;padding:.5em 0}
textarea{width:100%;height:6em}
"""


def _card(a: "Annotated") -> str:
    m = a.meta
    meta_rows = "".join(
        f"<tr><td>{_E(str(k))}</td><td>{_E(str(v))}</td></tr>"
        for k, v in m.items()
        if k not in ("sampled_keyframes", "q6_keep")
    )
    qa = "".join(
        f"<tr><td>{_E(r['id'].rsplit('_', 1)[-1])}</td><td class='q'>{_E(r['conversations'][0]['value'])}</td>"
        f"<td class='a'>{_E(r['conversations'][1]['value'])}</td></tr>"
        for r in a.records
    )
    tid = _E(a.trajectory, quote=True)
    return (
        f"<div class='card' data-trajectory=\"{tid}\" data-state='unmarked'>"
        f"<h3>{_E(a.trajectory)} &mdash; {_E(str(m.get('task', '')))} &mdash; <span class='state'>unmarked</span>"
        f"</h3><img src=\"{_E(a.image_name, quote=True)}\" alt='keyframe grid'>"
        f"<table>{qa}</table><details><summary>metadata</summary><table>{meta_rows}</table></details>"
        "<p><button data-mark='accept'>accept</button> <button data-mark='reject'>reject</button></p></div>"
    )


def write_review_page(items: list["Annotated"], path: Path, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pick = sorted(rng.choice(len(items), size=min(n, len(items)), replace=False).tolist()) if items else []
    cards = "\n".join(_card(items[i]) for i in pick)
    page = (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        "<meta http-equiv='Content-Security-Policy' content=\"default-src 'none'; img-src 'self' data: file:; "
        "style-src 'unsafe-inline'; script-src 'unsafe-inline'\">"
        f"<title>LabRobFail-Data review</title><style>{_STYLE}</style></head><body>"
        f"<div id='bar'><b>LabRobFail-Data review</b>: {len(pick)} sampled trajectories, "
        "<span id='count'>0</span> marked. <button id='export'>export marks (JSON)</button>"
        "<a id='download' style='display:none'>download</a>"
        "<textarea id='marks-json' readonly></textarea></div>"
        f"{cards}<script>{_SCRIPT}</script></body></html>"
    )
    atomic_write_bytes(path, page.encode())
