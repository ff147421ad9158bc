"""The interactive 3-D viewer of report.html: self-contained, offline, drawn by plotly.js.

The page holds plotly.js itself (``plotly.offline.get_plotlyjs()``, MIT licence) and the model as
base64 arrays: the mean (float32), the first modes already scaled by their standard deviation
sqrt(lambda_k) (float32), each scaled mode's component along the mean's outward normals (float32,
the colour), the triangles of each part (int32) and the aligned training shapes (uint16, quantised
on the bounding box of all cases: a step below 1/65535 of its size, to keep the page small; at most
``MAX_CASE_BYTES`` of them, beyond which a sample spread evenly over the first mode's scores,
:func:`shown_cases`). plotly.js is 4.8 MB of the page; 100 cases of 2562 points add 2.6 MB.

A few lines of JavaScript turn the sliders into ``mean + sum_k s_k sqrt(lambda_k) mode_k`` and the
colour into the displacement from the mean along the mean's outward normal, and call
``Plotly.restyle``; the case picker shows one corresponded case instead (coloured the same way).
One ``mesh3d`` trace per part: the legend toggles the parts. The landmarks of a guided build are a
``scatter3d`` trace of their labelled points, which follow the sliders and the picked case (they are
rows of the points). A model of 2-D curves is drawn as its
segments (a 2-D ``scatter`` per part, the points coloured). No network request: nothing is loaded
from anywhere but the page.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass

import numpy as np

from ..model.normals import outward_normals

MAX_MODES = 10
# the case picker's share of the page (bytes before base64: 6 per point and case); a population
# beyond it is shown by a sample of its cases (shown_cases), said on the page (2562 points: 260)
MAX_CASE_BYTES = 4_000_000
SD_RANGE = 3.0
# shown_cases scores this many cases at a time: their differences from the mean, not all the
# population's at once (n_s x n_p x 3 doubles), are what it holds
SCORED_AT_ONCE = 256


def _b64(array: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def correspondence_values(reference: np.ndarray) -> np.ndarray:
    """A value in [0, 1] per point, defined on the point index through ``reference`` (the
    mean): rising along its longest principal axis, with a light checker of bands and sectors
    around it, so that the same region gets the same colour on every corresponded case."""
    from .rendering import principal_axes

    centre, axes = principal_axes(reference)
    local = (np.asarray(reference, float) - centre) @ axes.T
    along = (local[:, 0] - local[:, 0].min()) / max(float(np.ptp(local[:, 0])), 1e-12)
    checker = np.cos(8 * np.pi * along) * np.cos(4 * np.arctan2(local[:, 2], local[:, 1]))
    return np.clip(0.9 * along + 0.05 + 0.05 * np.tanh(2.5 * checker), 0.0, 1.0)


def shown_cases(model, shapes: np.ndarray, limit: int) -> np.ndarray:
    """The cases (indices, in their order) the viewer holds: all of them up to ``limit``; beyond
    it ``limit`` cases at evenly spaced ranks of their score on the model's first mode, from the
    lowest to the highest (by their order where the model has no mode), so that the sample spans
    the population's main variation and is the same at every writing."""
    n_cases = len(shapes)
    if n_cases <= limit:
        return np.arange(n_cases)
    order = np.arange(n_cases)
    if model.n_modes > 0:
        weighted = np.asarray(model.modes[0]) * np.asarray(model.weights)[:, None]
        scores = np.concatenate([
            np.einsum("pd,spd->s", weighted, np.asarray(shapes[start:start + SCORED_AT_ONCE])
                      - model.mean) for start in range(0, n_cases, SCORED_AT_ONCE)])
        order = np.argsort(scores, kind="stable")
    ranks = np.unique(np.rint(np.linspace(0, n_cases - 1, limit)).astype(np.int64))
    return np.sort(order[ranks])


def viewer_data(model, shapes=None, names=None, n_modes: int = MAX_MODES,
                distances=None) -> dict:
    """What the page's script needs, as JSON-ready values (arrays base64-encoded).
    ``distances`` (n_cases, n_p): each corresponded point's distance to its case's own input
    surface (mm), which colours a case in the picker."""
    mean = np.asarray(model.mean, dtype=np.float64)
    triangles = np.asarray(model.triangles, dtype=np.int64)
    n_p = len(mean)
    k = max(0, min(int(n_modes), int(model.n_modes)))
    sds = np.sqrt(np.maximum(np.asarray(model.variances[:k], dtype=np.float64), 0.0))
    scaled = np.asarray(model.modes[:k], dtype=np.float64) * sds[:, None, None]   # (k, n_p, 3)
    part_of = model.part_of_triangles()
    normals = outward_normals(mean, triangles, part_of)
    along = np.einsum("kpd,pd->kp", scaled, normals)                             # (k, n_p)

    # one fixed colour range and one fixed box, so that nothing jumps as the sliders move
    half = float(SD_RANGE * np.abs(along).max(initial=0.0))
    extremes = [mean] + [mean + s * SD_RANGE * scaled[j] for j in range(k) for s in (-1, 1)]
    cases, n_cases = [], 0
    if shapes is not None and len(shapes):
        n_cases = len(shapes)
        shown = shown_cases(model, np.asarray(shapes, dtype=np.float64),
                            max(1, MAX_CASE_BYTES // (6 * n_p)))
        shapes = np.asarray(shapes, dtype=np.float64)[shown]
        displacement = np.einsum("spd,pd->sp", shapes - mean, normals)
        half = max(half, float(np.percentile(np.abs(displacement), 99)))
        extremes.append(shapes.reshape(-1, 3))
        low, high = shapes.min(axis=(0, 1)), shapes.max(axis=(0, 1))
        step = np.where(high > low, (high - low) / 65535.0, 1.0)
        quantised = np.rint((shapes - low) / step).clip(0, 65535)
        names = list(names) if names is not None else []
        cases = [str(names[i]) if i < len(names) else f"case {i + 1}" for i in shown]
    every = np.concatenate([np.reshape(e, (-1, 3)) for e in extremes])
    low_box, high_box = every.min(axis=0), every.max(axis=0)
    margin = 0.03 * float(np.max(high_box - low_box) or 1.0)
    ranges = [[float(low_box[d] - margin), float(high_box[d] + margin)] for d in range(3)]

    parts = []
    for index, part in enumerate(model.part_meshes()):
        parts.append({"name": part.name or "shape", "start": int(part.rows.start),
                      "stop": int(part.rows.stop),
                      "triangles": _b64(part.triangles, np.int32)})
    data = {
        "kind": "curve" if model.of_curves else "mesh",
        "n_points": n_p, "n_modes": k, "sd_range": SD_RANGE,
        "sds": [float(s) for s in sds], "half_range": half if half > 0 else 1.0,
        "ranges": ranges, "parts": parts,
        "mean": _b64(mean, np.float32), "modes": _b64(scaled, np.float32),
        "along": _b64(along, np.float32), "normals": _b64(normals, np.float32),
        "cases": cases, "n_cases": n_cases,
        "pattern": _b64(correspondence_values(mean), np.float32),
        "landmarks": [] if model.of_curves else [
            {"label": str(label), "row": int(row)} for label, row in model.landmarks.items()],
    }
    if cases:
        data.update(case_low=[float(v) for v in low], case_step=[float(v) for v in step],
                    case_points=_b64(quantised, np.uint16))
        if distances is not None and np.shape(distances) == (n_cases, n_p):
            kept = np.asarray(distances, dtype=np.float64)[shown]
            top = float(np.percentile(kept, 99.5)) or 1.0
            data.update(distance_max=top,
                        case_distance=_b64(np.rint(np.clip(kept / top, 0, 1) * 255), np.uint8))
    return data


SCRIPT = r"""
(function () {
  var D = JSON.parse(document.getElementById('viewer-data').textContent);
  function bytes(text) {
    var raw = atob(text), out = new Uint8Array(raw.length);
    for (var i = 0; i < raw.length; i++) out[i] = raw.charCodeAt(i);
    return out.buffer;
  }
  var n = D.n_points, K = D.n_modes;
  var mean = new Float32Array(bytes(D.mean)), modes = new Float32Array(bytes(D.modes));
  var along = new Float32Array(bytes(D.along)), normals = new Float32Array(bytes(D.normals));
  var cases = D.cases.length ? new Uint16Array(bytes(D.case_points)) : null;
  var pattern = new Float32Array(bytes(D.pattern));
  var distance = D.case_distance ? new Uint8Array(bytes(D.case_distance)) : null;
  var colouring = document.getElementById('viewer-colour');
  var SCALES = {   // plotly.js's RdBu runs from blue (low) to red (high): inward blue, as the
                   // report's renderings
    normal: {cmin: -D.half_range, cmax: D.half_range, colorscale: 'RdBu',
             title: 'normal<br>displacement<br>[mm]'},
    index: {cmin: 0, cmax: 1, colorscale: 'Rainbow', title: 'point<br>index'},
    distance: {cmin: 0, cmax: D.distance_max || 1, colorscale: 'Viridis',
               title: 'distance to<br>the input<br>[mm]'}};
  var s = new Float64Array(K), pending = false, curve = D.kind === 'curve';
  var cells = D.parts.map(function (part) { return new Int32Array(bytes(part.triangles)); });
  var div = document.getElementById('viewer-plot'), picker = document.getElementById('viewer-case');
  var marks = D.landmarks || [];

  function model() {               // mean + sum_k s_k sqrt(lambda_k) mode_k, normal displacement
    var p = Float64Array.from(mean), c = new Float64Array(n);
    for (var k = 0; k < K; k++) {
      if (s[k] === 0) continue;
      var m = modes.subarray(k * 3 * n, (k + 1) * 3 * n), a = along.subarray(k * n, (k + 1) * n);
      for (var i = 0; i < 3 * n; i++) p[i] += s[k] * m[i];
      for (var j = 0; j < n; j++) c[j] += s[k] * a[j];
    }
    return [p, c];
  }
  function training(index) {       // one aligned case, coloured by its normal displacement
    var p = new Float64Array(3 * n), c = new Float64Array(n), q = cases.subarray(index * 3 * n);
    for (var i = 0; i < n; i++) {
      for (var d = 0; d < 3; d++) p[3 * i + d] = D.case_low[d] + q[3 * i + d] * D.case_step[d];
      for (var e = 0; e < 3; e++) c[i] += (p[3 * i + e] - mean[3 * i + e]) * normals[3 * i + e];
    }
    return [p, c];
  }
  function traces(p, c) {          // per part: the points (surfaces) or the segments (curves)
    var out = {x: [], y: [], z: [], intensity: []};
    D.parts.forEach(function (part, j) {
      var x = [], y = [], z = [], t = [];
      if (curve) {                   // a, b, gap for each segment
        for (var f = 0; f < cells[j].length; f += 2) {
          var a = part.start + cells[j][f], b = part.start + cells[j][f + 1];
          x.push(p[3 * a], p[3 * b], null); y.push(p[3 * a + 1], p[3 * b + 1], null);
          t.push(c[a], c[b], null);
        }
      } else {
        for (var i = part.start; i < part.stop; i++) {
          x.push(p[3 * i]); y.push(p[3 * i + 1]); z.push(p[3 * i + 2]); t.push(c[i]);
        }
      }
      out.x.push(x); out.y.push(y); out.z.push(z); out.intensity.push(t);
    });
    return curve ? {x: out.x, y: out.y, 'marker.color': out.intensity} : out;
  }
  function landmarks(p) {          // the landmarks' points of a shape, as one trace's x, y, z
    var x = [], y = [], z = [];
    marks.forEach(function (mark) {
      x.push(p[3 * mark.row]); y.push(p[3 * mark.row + 1]); z.push(p[3 * mark.row + 2]);
    });
    return {x: [x], y: [y], z: [z]};
  }
  function current() {
    var pick = picker ? picker.value : '', mode = colouring ? colouring.value : 'normal';
    var shape = pick === '' ? model() : training(Number(pick));
    if (mode === 'index') shape[1] = pattern;
    if (mode === 'distance') {          // a case's own distances; none for the model itself
      var c = new Float64Array(n);
      if (pick !== '' && distance) {
        var q = distance.subarray(Number(pick) * n, (Number(pick) + 1) * n);
        for (var i = 0; i < n; i++) c[i] = q[i] / 255 * D.distance_max;
      }
      shape[1] = c;
    }
    return shape;
  }
  function recolour() {
    var scale = SCALES[colouring.value];
    Plotly.relayout(div, {'coloraxis.cmin': scale.cmin, 'coloraxis.cmax': scale.cmax,
                          'coloraxis.colorscale': scale.colorscale,
                          'coloraxis.colorbar.title.text': scale.title});
    later();
  }
  function draw() {
    pending = false;
    var shape = current();
    Plotly.restyle(div, traces.apply(null, shape), D.parts.map(function (_, i) { return i; }));
    if (marks.length) Plotly.restyle(div, landmarks(shape[0]), [D.parts.length]);
  }
  function later() { if (!pending) { pending = true; requestAnimationFrame(draw); } }

  var start = model(), first = traces.apply(null, start);
  var data = D.parts.map(function (part, i) {
    if (curve) {
      return {type: 'scatter', mode: 'lines+markers', name: part.name, x: first.x[i],
              y: first.y[i], line: {color: '#777', width: 1.5}, hoverinfo: 'skip',
              marker: {color: first['marker.color'][i], coloraxis: 'coloraxis', size: 7},
              showlegend: D.parts.length > 1};
    }
    var tri = cells[i], I = [], J = [], L = [];
    for (var f = 0; f < tri.length; f += 3) {
      I.push(tri[f]); J.push(tri[f + 1]); L.push(tri[f + 2]);
    }
    return {type: 'mesh3d', name: part.name, x: first.x[i], y: first.y[i], z: first.z[i],
            i: I, j: J, k: L, intensity: first.intensity[i], intensitymode: 'vertex',
            coloraxis: 'coloraxis', showlegend: D.parts.length > 1, flatshading: false,
            hoverinfo: 'skip', lighting: {ambient: 0.6, diffuse: 0.6, specular: 0.1}};
  });
  if (marks.length) {
    var at = landmarks(start[0]), names = marks.map(function (mark) { return mark.label; });
    data.push({type: 'scatter3d', mode: 'markers+text', name: 'landmarks', x: at.x[0],
               y: at.y[0], z: at.z[0], text: names, hovertext: names, hoverinfo: 'text',
               textposition: 'top center', textfont: {size: 11, color: '#111'},
               marker: {size: 4, color: '#111'}, showlegend: true});
  }
  var box = D.ranges, size = box.map(function (r) { return r[1] - r[0]; });
  var big = Math.max.apply(null, size);
  var axis = function (r) { return {range: r, visible: false}; };
  var layout = {
    margin: {l: 0, r: 0, t: 0, b: 0}, paper_bgcolor: '#ffffff', uirevision: 'keep',
    legend: {x: 0, y: 1},
    coloraxis: {cmin: SCALES.normal.cmin, cmax: SCALES.normal.cmax,
                colorscale: SCALES.normal.colorscale,
                colorbar: {title: {text: SCALES.normal.title}, len: 0.8}}};
  if (curve) {                       // 2-D: equal scales on x and y
    layout.plot_bgcolor = '#ffffff';
    layout.xaxis = {range: box[0], visible: false, constrain: 'domain'};
    layout.yaxis = {range: box[1], visible: false, scaleanchor: 'x', scaleratio: 1,
                    constrain: 'domain'};
  } else {
    layout.scene = {xaxis: axis(box[0]), yaxis: axis(box[1]), zaxis: axis(box[2]),
                    aspectmode: 'manual', camera: {eye: {x: 0.8, y: 0.8, z: 0.55}},
                    aspectratio: {x: size[0] / big, y: size[1] / big, z: size[2] / big}};
  }
  Plotly.newPlot(div, data, layout,
                 {displaylogo: false, responsive: true, modeBarButtonsToRemove: ['toImage']});

  document.querySelectorAll('#viewer input[type=range]').forEach(function (slider) {
    slider.addEventListener('input', function () {
      var k = Number(slider.dataset.mode);
      s[k] = Number(slider.value);
      document.getElementById('viewer-sd-' + k).textContent = s[k].toFixed(1);
      if (picker) picker.value = '';
      later();
    });
  });
  if (picker) picker.addEventListener('change', later);
  if (colouring) colouring.addEventListener('change', recolour);
  var reset = document.getElementById('viewer-reset');
  reset.addEventListener('click', function () {
    document.querySelectorAll('#viewer input[type=range]').forEach(function (slider) {
      slider.value = 0; s[Number(slider.dataset.mode)] = 0;
      document.getElementById('viewer-sd-' + slider.dataset.mode).textContent = '0.0';
    });
    if (picker) picker.value = '';
    later();
  });
})();
"""

STYLE = ("#viewer .controls{display:flex;flex-wrap:wrap;gap:4px 18px;margin:0.5em 0}"
         "#viewer label{font-size:90%;white-space:nowrap}#viewer input[type=range]{width:140px;"
         "vertical-align:middle}#viewer-plot{width:100%;height:560px;border:1px solid #ddd}"
         "#viewer .licence{font-size:80%;color:#666}")


def _plotly_js() -> str:
    from plotly.offline import get_plotlyjs

    return get_plotlyjs().replace("</script", "<\\/script")


def viewer_section(model, shapes=None, names=None, n_modes: int = MAX_MODES,
                   distances=None, prefix: str = "viewer",
                   heading: str = "<h2>Interactive viewer</h2>", with_plotly: bool = True) -> list:
    """The report's interactive viewer (HTML fragments), or a note where it does not apply.
    ``distances`` (n_cases, n_p, optional): each corresponded point's distance to its case's
    input surface, offered as the colour of a case. Several viewers share a page when each has
    its own ``prefix`` (of its element ids) and only the first carries plotly.js
    (``with_plotly``)."""
    if model is None:
        return []
    if model.triangles is None or len(model.triangles) == 0:
        return [heading, "<p>No interactive viewer: the model has no triangles.</p>"]
    try:
        plotly_js = _plotly_js()
    except ImportError as error:
        return [heading, f"<p>No interactive viewer: plotly is not installed "
                         f"({html.escape(str(error))}).</p>"]
    data = viewer_data(model, shapes, names, n_modes, distances)
    k = data["n_modes"]
    sliders = "".join(
        f"<label>mode {j + 1} <input type=range id='viewer-mode-{j}' data-mode={j} "
        f"min={-SD_RANGE:g} max={SD_RANGE:g} step=0.1 value=0> <span id='viewer-sd-{j}'>0.0</span>"
        f" SD</label>" for j in range(k))
    picker = ""
    if data["cases"]:
        options = "".join(f"<option value={i}>{html.escape(name)}</option>"
                          for i, name in enumerate(data["cases"]))
        picker = (f"<label>show <select id='viewer-case'><option value='' selected>the model "
                  f"(sliders)</option>{options}</select></label>")
    choices = [("normal", "displacement along the normal"),
               ("index", "point index (the correspondence)")]
    if "case_distance" in data:
        choices.append(("distance", "a case's distance to its input surface"))
    colour = ("<label>colour <select id='viewer-colour'>" + "".join(
        f"<option value={value}>{html.escape(text)}</option>" for value, text in choices)
        + "</select></label>")
    parts_note = (" Click a part's name in the legend to hide or show it."
                  if len(data["parts"]) > 1 else "")
    if data["landmarks"]:
        parts_note += (" The black points are the landmarks that guided the build, where they "
                       "lie on the shape shown; the legend hides them.")
    payload = json.dumps(data).replace("</", "<\\/")
    shown = (f": a sample of {len(data['cases'])} of the {data['n_cases']} cases, at evenly "
             f"spaced ranks of their score on mode 1 (from the lowest to the highest), to keep "
             f"the page small" if len(data["cases"]) < data["n_cases"] else "")
    how = ("Drag a box to zoom, double-click to see all" if model.of_curves
           else "Drag to turn, scroll to zoom")
    fragments = [
        heading,
        f"<style>{STYLE}</style>",
        "<div id=viewer>",
        f"<p>{how}. Each slider moves along one of the first {k} modes "
        f"(-{SD_RANGE:g} to +{SD_RANGE:g} standard deviations); colour: displacement from the "
        f"mean along the mean's outward normal (mm), or the point index (the same colour is "
        f"the same model point on every case), or a case's distance to its own input surface. "
        f"The case picker shows a corresponded training case (aligned){shown}.{parts_note}</p>",
        f"<div class=controls>{sliders}</div>",
        f"<div class=controls>{picker} {colour} <button id='viewer-reset' type=button>mean "
        f"shape</button></div>",
        "<div id='viewer-plot'></div>",
        "<p class=licence>Drawn with plotly.js (MIT licence, Copyright (c) Plotly, Inc.), "
        "embedded in this page: it works offline.</p>",
        "</div>",
        f"<script>{plotly_js}</script>" if with_plotly else "",
        f"<script type='application/json' id='viewer-data'>{payload}</script>",
        f"<script>{SCRIPT}</script>",
    ]
    if prefix == "viewer":
        return fragments
    return [fragment.replace("'viewer-", f"'{prefix}-").replace("#viewer", f"#{prefix}")
            .replace("id=viewer>", f"id={prefix}>") for fragment in fragments]


# ---------------------------------------------------------------------------------------------
# the analysis page: effect maps on the mean surface, with a threshold

EFFECT_SCRIPT = r"""
(function () {
  var D = JSON.parse(document.getElementById('effects-data').textContent);
  function floats(text) {
    var bytes = Uint8Array.from(atob(text), function (c) { return c.charCodeAt(0); });
    return new Float32Array(bytes.buffer);
  }
  function ints(text) {
    var bytes = Uint8Array.from(atob(text), function (c) { return c.charCodeAt(0); });
    return new Int32Array(bytes.buffer);
  }
  var mean = floats(D.mean), cells = ints(D.triangles), n = D.n_points;
  var maps = D.maps.map(function (m) { return {name: m.name, values: floats(m.values),
                                              diverging: m.diverging, limit: m.limit,
                                              ticks: m.ticks, labels: m.labels,
                                              points: m.points ? floats(m.points) : null}; });
  function coordinates(map) {     // the map's own shape (a group's mean), else the mean
    var source = map.points || mean, out = {x: [], y: [], z: []};
    for (var p = 0; p < n; p++) { out.x.push(source[3 * p]); out.y.push(source[3 * p + 1]);
                                  out.z.push(source[3 * p + 2]); }
    return out;
  }
  var I = [], J = [], K = [], shape = coordinates(maps[0]);
  var x = shape.x, y = shape.y, z = shape.z;
  for (var t = 0; t < cells.length; t += 3) { I.push(cells[t]); J.push(cells[t + 1]);
                                              K.push(cells[t + 2]); }
  var choice = document.getElementById('effects-map');
  var threshold = document.getElementById('effects-threshold');
  var shown = document.getElementById('effects-threshold-value');
  function colours() {
    var map = maps[+choice.value], level = +threshold.value * map.limit, out = [];
    for (var p = 0; p < n; p++) {
      var v = map.values[p];
      out.push(Math.abs(v) >= level ? v : 0);   // below the threshold: the neutral colour
    }
    shown.textContent = (level).toPrecision(3);
    return out;
  }
  function scale() {              // the map's fixed range; its marked values on the colour bar
    var map = maps[+choice.value];
    var out = map.diverging ? {cmin: -map.limit, cmax: map.limit, colorscale: 'RdBu'}
                            : {cmin: 0, cmax: map.limit, colorscale: 'Viridis'};
    out.ticks = map.ticks.length ? {tickmode: 'array', tickvals: map.ticks, ticktext: map.labels}
                                 : {tickmode: 'auto', tickvals: null, ticktext: null};
    return out;
  }
  function bar(s, name) {
    return Object.assign({title: {text: name}, len: 0.8}, s.ticks);
  }
  var layout = {margin: {l: 0, r: 0, t: 0, b: 0}, uirevision: 'keep',
                scene: {xaxis: {visible: false}, yaxis: {visible: false},
                        zaxis: {visible: false}, aspectmode: 'data',
                        camera: {eye: {x: D.eye[0], y: D.eye[1], z: D.eye[2]}}}};
  var first = scale();
  var trace = {type: 'mesh3d', x: x, y: y, z: z, i: I, j: J, k: K, intensity: colours(),
               intensitymode: 'vertex', hoverinfo: 'skip', flatshading: false,
               cmin: first.cmin, cmax: first.cmax, colorscale: first.colorscale,
               colorbar: bar(first, maps[0].name),
               lighting: {ambient: 0.6, diffuse: 0.6, specular: 0.1}};
  Plotly.newPlot('effects-plot', [trace], layout, {displaylogo: false, responsive: true});
  function update() {
    var s = scale(), c = coordinates(maps[+choice.value]);
    Plotly.restyle('effects-plot', {intensity: [colours()], cmin: [s.cmin], cmax: [s.cmax],
                                    x: [c.x], y: [c.y], z: [c.z],
                                    colorscale: [s.colorscale],
                                    colorbar: [bar(s, maps[+choice.value].name)]});
  }
  choice.addEventListener('change', update);
  threshold.addEventListener('input', update);
})();
"""


@dataclass(frozen=True)
class EffectMap:
    """One map of :func:`effects_section`: a value per point of the mean surface.

    ``diverging``: coloured symmetrically about 0, blue negative; else from 0 up. ``limit``: the
    colour scale's end (the largest |value| shown at full colour), fixed whatever the values, so
    that a map of small values looks small; None: the map's largest |value|. ``marks``: values
    marked on the colour bar, with their labels (such as the significance level)."""

    name: str
    values: np.ndarray
    diverging: bool = False
    limit: float | None = None
    marks: tuple = ()          # ((value, label), ...)
    points: np.ndarray | None = None   # (p, 3) the surface it is drawn on; None: the mean

    def scale_end(self) -> float:
        """The colour scale's end: ``limit``, or the largest |value| (1 when all are 0)."""
        if self.limit is not None:
            return float(self.limit)
        return float(np.max(np.abs(self.values), initial=0.0)) or 1.0

    def ticks(self) -> tuple[list, list]:
        """The colour bar's ticks: the scale's ends, 0 and the marks (values, labels); none
        (plotly's own) without marks."""
        if not self.marks:
            return [], []
        end = self.scale_end()
        ticks = {-end: f"{-end:.3g}", 0.0: "0", end: f"{end:.3g}"} if self.diverging else {
            0.0: "0", end: f"{end:.3g}"}
        ticks.update({float(value): label for value, label in self.marks})
        ordered = sorted(ticks)
        return ordered, [ticks[value] for value in ordered]


def effects_section(mean: np.ndarray, triangles: np.ndarray, maps: list) -> list:
    """An interactive 3-D view of effect maps on the mean surface (HTML fragments): a picker of
    the ``maps`` (:class:`EffectMap`), each on its fixed colour scale with its marks on the
    colour bar, and a threshold below which a point shows the neutral colour (a share of the
    scale's end). A map with its own ``points`` is drawn on that shape (a group's mean shape):
    choosing between two such maps switches between the shapes. Offline: plotly.js inlined."""
    if triangles is None or len(triangles) == 0 or np.shape(triangles)[1] != 3:
        return []
    try:
        plotly_js = _plotly_js()
    except ImportError:
        return []
    # the camera looks at the first map's strongest point, from outside the surface
    strongest = np.asarray(mean)[int(np.argmax(np.abs(maps[0].values)))] - np.mean(mean, axis=0)
    eye = 2.0 * strongest / (np.linalg.norm(strongest) or 1.0)
    encoded = []
    for effect in maps:
        ticks, labels = effect.ticks()
        encoded.append({"name": effect.name,
                        "values": _b64(np.asarray(effect.values), np.float32),
                        "diverging": bool(effect.diverging), "limit": effect.scale_end(),
                        "ticks": ticks, "labels": labels,
                        "points": (None if effect.points is None
                                   else _b64(np.asarray(effect.points), np.float32))})
    data = {"eye": [float(v) for v in eye],
            "n_points": int(len(mean)), "mean": _b64(np.asarray(mean), np.float32),
            "triangles": _b64(np.asarray(triangles), np.int32), "maps": encoded}
    options = "".join(f"<option value={k}>{html.escape(effect.name)}</option>"
                      for k, effect in enumerate(maps))
    payload = json.dumps(data).replace("</", "<\\/")
    return [
        "<h3>Turn it yourself</h3>",
        "<p>Drag to turn, scroll to zoom; choose the map, and grey out the points whose value "
        "is below the threshold (a share of the colour scale's end). Each map keeps one colour "
        "scale: -log10 p runs from 0 to at least -log10 &alpha; (marked on the colour bar), so "
        "that where nothing is significant nothing is bright.</p>",
        "<div id=effects><div class=controls>"
        f"<label>map <select id='effects-map'>{options}</select></label> "
        "<label>threshold <input type=range id='effects-threshold' min=0 max=1 step=0.01 "
        "value=0> <span id='effects-threshold-value'>0</span></label></div>",
        "<div id='effects-plot' style='width:100%;height:520px;border:1px solid #ddd'></div>",
        "<p style='font-size:80%;color:#666'>Drawn with plotly.js (MIT licence, Copyright (c) "
        "Plotly, Inc.), embedded in this page: it works offline.</p></div>",
        f"<script>{plotly_js}</script>",
        f"<script type='application/json' id='effects-data'>{payload}</script>",
        f"<script>{EFFECT_SCRIPT}</script>",
    ]
