"""A self-contained HTML report: figures embedded as data URIs, no network needed.

Used by ``prism3d demo``. Each pipeline stage contributes a :class:`Section` of
paragraphs, tables (with units in the column names) and figures; artefacts written
to the output folder are linked relative to the report.
"""

from __future__ import annotations

import base64
import html
import io
import platform
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from prism3d import __version__
from prism3d.io.atomic import atomic_write_text

__all__ = ["Section", "Report", "figure_png", "image_png", "point_cloud_viewer"]

# A small self-contained point-cloud viewer: 2-D canvas, no WebGL (works in headless
# browsers without a GPU), drag to rotate, wheel to zoom, painter's algorithm by depth.
_VIEWER_JS = """
(function(){
  function start(id){
    var el=document.getElementById(id), cv=el.querySelector('canvas'), ctx=cv.getContext('2d');
    var d=JSON.parse(el.querySelector('script[type="application/json"]').textContent);
    var P=d.p, C=d.c, n=P.length/3, yaw=0.6, pitch=-0.35, zoom=1.0, drag=null;
    var cx=0,cy=0,cz=0,r=0,i;
    for(i=0;i<n;i++){cx+=P[3*i];cy+=P[3*i+1];cz+=P[3*i+2];}
    cx/=n;cy/=n;cz/=n;
    for(i=0;i<n;i++){var dx=P[3*i]-cx,dy=P[3*i+1]-cy,dz=P[3*i+2]-cz;r=Math.max(r,Math.sqrt(dx*dx+dy*dy+dz*dz));}
    var order=new Array(n), depth=new Float32Array(n), sx=new Float32Array(n), sy=new Float32Array(n);
    function draw(){
      var w=cv.width,h=cv.height,s=zoom*0.45*Math.min(w,h)/r;
      var cyw=Math.cos(yaw),syw=Math.sin(yaw),cp=Math.cos(pitch),sp=Math.sin(pitch);
      for(var k=0;k<n;k++){
        var x=P[3*k]-cx,y=P[3*k+1]-cy,z=P[3*k+2]-cz;
        var x1=cyw*x+syw*z, z1=-syw*x+cyw*z;
        var y2=cp*y-sp*z1, z2=sp*y+cp*z1;
        sx[k]=w/2+s*x1; sy[k]=h/2+s*y2; depth[k]=z2; order[k]=k;
      }
      order.sort(function(a,b){return depth[b]-depth[a];});
      ctx.fillStyle='#ffffff'; ctx.fillRect(0,0,w,h);
      for(var j=0;j<n;j++){var q=order[j];
        ctx.fillStyle='rgb('+C[3*q]+','+C[3*q+1]+','+C[3*q+2]+')';
        ctx.fillRect(sx[q]-1,sy[q]-1,2.2,2.2);}
    }
    cv.addEventListener('mousedown',function(e){drag=[e.clientX,e.clientY];});
    window.addEventListener('mouseup',function(){drag=null;});
    window.addEventListener('mousemove',function(e){if(!drag)return;
      yaw+=(e.clientX-drag[0])*0.01; pitch+=(e.clientY-drag[1])*0.01; drag=[e.clientX,e.clientY]; draw();});
    cv.addEventListener('wheel',function(e){e.preventDefault();zoom*=e.deltaY<0?1.1:1/1.1;draw();},{passive:false});
    el.setAttribute('data-points', String(n)); draw(); el.setAttribute('data-ready','1');
  }
  document.querySelectorAll('.p3d-viewer').forEach(function(e){start(e.id);});
})();
"""

# Marks the page with how many figures decoded (``data-images-ok`` / ``data-images``
# on <body>), so a headless browser check can tell that every image rendered.
_HEALTH_JS = """
window.addEventListener('load',function(){
  var imgs=document.images, ok=0;
  for(var i=0;i<imgs.length;i++){ if(imgs[i].complete && imgs[i].naturalWidth>0) ok++; }
  document.body.setAttribute('data-images', String(imgs.length));
  document.body.setAttribute('data-images-ok', String(ok));
});
"""


def point_cloud_viewer(points: np.ndarray, colors: np.ndarray | None, *, max_points: int = 25000,
                       element_id: str = "viewer3d", width: int = 820, height: int = 560) -> str:
    """HTML of an interactive (drag to rotate, wheel to zoom) view of a coloured point
    cloud, self-contained (data inline, no WebGL, no network).

    The camera-frame y axis points down, so the cloud is shown with y up.
    """
    import json

    p = np.asarray(points, dtype=np.float64)
    c = np.full((len(p), 3), 90, np.uint8) if colors is None else np.asarray(colors, dtype=np.uint8)
    if len(p) > max_points:
        idx = np.random.default_rng(0).choice(len(p), max_points, replace=False)
        p, c = p[idx], c[idx]
    p = p * np.array([1.0, -1.0, 1.0])  # y up on screen
    data = json.dumps({"p": np.round(p, 2).ravel().tolist(), "c": c.ravel().tolist()}, separators=(",", ":"))
    return (f"<div class='p3d-viewer' id='{html.escape(element_id)}'>"
            f"<canvas width='{width}' height='{height}' style='border:1px solid #dde3ea;cursor:grab'></canvas>"
            f"<script type='application/json'>{data}</script>"
            "<p class='meta'>Drag to rotate, scroll to zoom.</p></div>")


def image_png(image: np.ndarray, *, max_side: int = 900) -> bytes:
    """Encode an RGB/grey uint8 image as PNG bytes, downscaled to ``max_side``."""
    import cv2

    img = np.asarray(image)
    scale = max_side / max(img.shape[:2])
    if scale < 1:
        img = cv2.resize(img, (int(img.shape[1] * scale), int(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    if img.ndim == 3:
        img = img[:, :, ::-1]
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8
        raise RuntimeError("PNG encoding failed")
    return enc.tobytes()


def figure_png(fig: Any, *, dpi: int = 110) -> bytes:
    """Render a matplotlib figure to PNG bytes and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


@dataclass
class Section:
    """One stage's part of the report."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[tuple[str, list[str], list[list[Any]]]] = field(default_factory=list)
    figures: list[tuple[str, bytes]] = field(default_factory=list)
    links: list[tuple[str, str]] = field(default_factory=list)
    raw_html: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def table(self, caption: str, header: list[str], rows: list[list[Any]]) -> None:
        self.tables.append((caption, header, rows))

    def figure(self, caption: str, png: bytes) -> None:
        self.figures.append((caption, png))

    def link(self, label: str, relpath: str) -> None:
        self.links.append((label, relpath))


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return "–"
        a = abs(float(v))
        if a != 0 and (a < 1e-3 or a >= 1e6):
            return f"{float(v):.3e}"
        return f"{float(v):.4g}"
    return html.escape(str(v))


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;
padding:0 1em;color:#1d2330;line-height:1.45}
h1{font-size:1.7em;margin-bottom:.2em} h2{border-bottom:2px solid #dde3ea;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em} caption{text-align:left;font-weight:600;padding:.3em 0}
th,td{border:1px solid #cfd6de;padding:.3em .6em;text-align:right} th{background:#f0f3f7}
td:first-child,th:first-child{text-align:left}
figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top} figcaption{font-size:.85em;color:#555}
figure img{max-width:100%;border:1px solid #dde3ea} .meta{color:#667;font-size:.9em}
.links a{margin-right:1em} .time{color:#889;font-size:.85em;font-weight:normal}
"""


class Report:
    """Collects sections and writes one self-contained HTML file."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.sections: list[Section] = []
        self.created = datetime.now(timezone.utc)

    def add(self, section: Section) -> None:
        self.sections.append(section)

    def to_html(self) -> str:
        parts = [
            "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
            f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head><body>",
            f"<h1>{html.escape(self.title)}</h1>",
            f"<p class='meta'>prism3d {__version__} · {self.created:%Y-%m-%d %H:%M UTC} · "
            f"Python {platform.python_version()} · {html.escape(platform.machine())}</p>",
            "<ul>" + "".join(
                f"<li><a href='#s{i}'>{html.escape(s.title)}</a></li>" for i, s in enumerate(self.sections)
            ) + "</ul>",
        ]
        for i, s in enumerate(self.sections):
            parts.append(f"<h2 id='s{i}'>{html.escape(s.title)} "
                         f"<span class='time'>({s.seconds:.1f} s)</span></h2>")
            parts += [f"<p>{p}</p>" for p in s.paragraphs]
            for caption, header, rows in s.tables:
                parts.append(f"<table><caption>{html.escape(caption)}</caption><tr>"
                             + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
                parts += ["<tr>" + "".join(f"<td>{_fmt(v)}</td>" for v in r) + "</tr>" for r in rows]
                parts.append("</table>")
            for caption, png in s.figures:
                b64 = base64.b64encode(png).decode("ascii")
                parts.append(f"<figure><img alt='{html.escape(caption)}' src='data:image/png;base64,{b64}'>"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
            parts += s.raw_html
            if s.links:
                parts.append("<p class='links'>Files: " + "".join(
                    f"<a href='{html.escape(rel)}'>{html.escape(label)}</a>" for label, rel in s.links) + "</p>")
        if any("p3d-viewer" in h for sec in self.sections for h in sec.raw_html):
            parts.append(f"<script>{_VIEWER_JS}</script>")
        parts.append(f"<script>{_HEALTH_JS}</script>")
        parts.append("</body></html>")
        return "\n".join(parts)

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        atomic_write_text(path, self.to_html())
        return path
