"""Self-contained HTML pages: the report (images, tables, 3D twin) and the live-view shell. No network needed."""

from __future__ import annotations

import base64
import html
import json
from importlib import resources
from pathlib import Path
from typing import Any

from normpos_grasp.report.scene3d import TwinScene

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; background: #fafafa; }
h1 { font-size: 1.4em; } h2 { font-size: 1.1em; margin-top: 1.5em; }
table { border-collapse: collapse; font-size: 0.9em; } td, th { border: 1px solid #ccc; padding: 3px 8px; }
th { background: #eee; } img { max-width: 100%; border: 1px solid #ccc; }
#view { width: 100%; height: 560px; border: 1px solid #ccc; background: #f5f5f7; display: block; }
#status { font-size: 0.8em; color: #a00; min-height: 1em; } .hint { font-size: 0.8em; color: #666; }
pre { font-size: 0.8em; background: #fff; border: 1px solid #ddd; padding: 6px; max-height: 240px; overflow: auto; }
"""


def viewer_script() -> str:
    """The WebGL viewer's JavaScript source, shipped with the package."""
    return resources.files("normpos_grasp.report").joinpath("viewer.js").read_text(encoding="utf-8")


def table_html(rows: list[dict[str, Any]]) -> str:
    """An HTML table from a list of dicts sharing keys (values escaped)."""
    if not rows:
        return "<p>(none)</p>"
    keys = list(rows[0])
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(r.get(k, '')))}</td>" for k in keys) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def report_page(
    title: str,
    scene: TwinScene,
    images: dict[str, bytes],
    sections: dict[str, str],
) -> str:
    """A complete HTML page: `images` (caption -> PNG bytes, embedded), `sections` (heading -> HTML), the 3D scene."""
    parts = [f"<h1>{html.escape(title)}</h1>"]
    for heading, body in sections.items():
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    for caption, png in images.items():
        data = base64.b64encode(png).decode("ascii")
        parts.append(
            f"<h2>{html.escape(caption)}</h2><img alt='{html.escape(caption)}' src='data:image/png;base64,{data}'>"
        )
    parts.append(
        "<h2>3D digital twin</h2><canvas id='view'></canvas><div id='status'></div>"
        "<p class='hint'>drag: rotate, shift-drag: pan, wheel: zoom</p>"
    )
    payload = json.dumps(scene.to_payload()).replace("</", "<\\/")
    return _page(title, "".join(parts), payload, live=False)


def live_page(title: str) -> str:
    """The live view's page: polls /scene.json for the current frame and arm state."""
    body = (
        f"<h1>{html.escape(title)}</h1><canvas id='view'></canvas><div id='status'></div>"
        "<p class='hint'>live: updates every 0.5 s; drag: rotate, shift-drag: pan, wheel: zoom</p>"
        "<h2>Arm state</h2><pre id='arm-state'>waiting for data</pre>"
    )
    return _page(title, body, "", live=True)


def _page(title: str, body: str, payload: str, live: bool) -> str:
    live_flag = "<script>window.NORMPOS_LIVE = true;</script>" if live else ""
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>{body}"
        f"<script id='scene-data' type='application/json'>{payload}</script>{live_flag}"
        f"<script>{viewer_script()}</script></body></html>"
    )


def write_page(path: str | Path, page: str) -> None:
    """Write an HTML page atomically."""
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(target)
