"""The report's main result: the recovered envmap large, beside the chrome ball's and the truth's when they exist,
at one exposure with a slider (an inline script draws the linear maps into canvases: the page stays one file),
direction labels of the standard lat-long convention (+x at the centre, +y a quarter from the left) and the
horizon line.

Maps are passed as (H, 2H, 3) linear radiance in the standard file convention; the script gets them as base64
float32 and applies exposure 2^EV / ref, clip and gamma 1/2.2 (``ref``: :func:`reference` of the first map).
"""

from __future__ import annotations

import base64

import numpy as np

from objcam.report.html import esc

CSS = """
.envgrid { display: grid; grid-template-columns: repeat(auto-fit, minmax(480px, 1fr)); gap: 1rem; }
.envbox { position: relative; }
.envbox canvas { display: block; width: 100%; aspect-ratio: 2 / 1; image-rendering: pixelated; background: #222; }
.envbox .horizon { position: absolute; left: 0; right: 0; top: 50%; border-top: 1px dashed rgba(255,255,255,.8); }
.envbox .tag { position: absolute; font-size: .75rem; color: #fff; background: rgba(0,0,0,.55); padding: 0 .3em;
               border-radius: 3px; }
.envaxis { position: relative; height: 1.2rem; font-size: .78rem; color: #333; }
.envaxis span { position: absolute; top: 0; transform: translateX(-50%); white-space: nowrap; }
.envaxis span.first { transform: none; } .envaxis span.last { transform: translateX(-100%); }
.envctl { margin: .4rem 0 .8rem; font-size: .9rem; } .envctl input { vertical-align: middle; width: 14rem; }
"""

SCRIPT = """<script>
(function () {
  function floats(b64) {
    var s = atob(b64), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return new Float32Array(u.buffer);
  }
  function draw(c, ev) {
    var w = +c.width, h = +c.height, k = Math.pow(2, ev) / +c.dataset.ref, d = c._data;
    var ctx = c.getContext('2d'), im = ctx.createImageData(w, h);
    for (var i = 0; i < w * h; i++) {
      for (var ch = 0; ch < 3; ch++) {
        var v = Math.min(1, Math.max(0, d[3 * i + ch] * k));
        im.data[4 * i + ch] = Math.round(255 * Math.pow(v, 1 / 2.2));
      }
      im.data[4 * i + 3] = 255;
    }
    ctx.putImageData(im, 0, 0);
  }
  var canvases = document.querySelectorAll('canvas.envmap');
  for (var i = 0; i < canvases.length; i++) canvases[i]._data = floats(canvases[i].dataset.rgb);
  var sliders = document.querySelectorAll('input.exposure');
  for (var j = 0; j < sliders.length; j++) (function (inp) {
    var out = inp.parentNode.querySelector('output');
    function update() {
      var group = document.querySelectorAll('canvas.envmap[data-group="' + inp.dataset.group + '"]');
      for (var k = 0; k < group.length; k++) draw(group[k], +inp.value);
      out.textContent = (inp.value > 0 ? '+' : '') + inp.value + ' EV';
    }
    inp.addEventListener('input', update);
    update();
  })(sliders[j]);
})();
</script>"""

# u = 0.5 - atan2(y, x) / (2 pi): where each axis sits across the panorama (data_layout.md)
AXIS_LABELS = ((0.0, "\u2212x"), (0.25, "+y"), (0.5, "+x"), (0.75, "\u2212y"), (1.0, "\u2212x"))


def reference(env: np.ndarray) -> float:
    """The exposure reference: the white of evaluate's PNGs and scores (objcam.metrics.tonemap_scale) over the
    texels with light (unsolved ones are written as 0): the 99th percentile, or the maximum where that percentile
    is a flat background (a dark room's walls, which would otherwise open as one white); 1 for a black map."""
    from objcam.metrics import tonemap_scale

    rgb = np.nan_to_num(np.asarray(env, np.float64)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    lit = (rgb > 0).any(axis=-1)
    return tonemap_scale(rgb, lit) if lit.any() else 1.0


def _canvas(env: np.ndarray, group: str, ref: float, label: str) -> str:
    data = np.ascontiguousarray(np.nan_to_num(env[..., :3], nan=0.0, posinf=0.0), dtype="<f4")
    b64 = base64.b64encode(data.tobytes()).decode("ascii")
    h, w = env.shape[:2]
    axis = "".join(f'<span class="{"first" if u == 0 else "last" if u == 1 else ""}" style="left:{100 * u:g}%">'
                   f"{t}</span>" for u, t in AXIS_LABELS)
    return (f'<figure><div class="envbox"><canvas class="envmap" width="{w}" height="{h}" data-group="{esc(group)}" '
            f'data-ref="{ref!r}" data-rgb="{b64}" role="img" aria-label="{esc(label)}"></canvas>'
            '<div class="horizon"></div><span class="tag" style="left:.3rem;top:.2rem">zenith</span>'
            '<span class="tag" style="right:.3rem;top:calc(50% - 1.2rem)">horizon</span></div>'
            f'<div class="envaxis">{axis}</div><figcaption>{esc(label)}</figcaption></figure>')


def envmap_panel(group: str, maps: list[tuple[str, np.ndarray]], note: str = "", ref_index: int = 0) -> str:
    """The slider and one canvas per (caption, map): maps (H, 2H, 3) linear, standard file convention, already on
    one radiometric scale; the exposure reference is map ``ref_index``'s (the truth's when there is one)."""
    maps = [(c, m) for c, m in maps if m is not None]
    if not maps:
        return ""
    ref_caption, ref = maps[ref_index][0], reference(maps[ref_index][1])
    figs = "".join(_canvas(m, group, ref, c) for c, m in maps)
    ctl = (f'<div class="envctl"><label>exposure <input class="exposure" type="range" min="-8" max="8" step="0.5" '
           f'value="0" data-group="{esc(group)}"> <output>0 EV</output></label> <span class="meta">0 EV: '
           f'{esc(ref_caption)}\u2019s white ({ref:.3g}: its 99th percentile, its maximum where that is a flat '
           f'background), gamma 1/2.2. {esc(note)}</span></div>')
    return ctl + f'<div class="envgrid">{figs}</div>'
