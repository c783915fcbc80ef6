/* faceretarget report viewer: a small canvas-2D mesh renderer (no external libraries).
   Data: <script id="report-data" type="application/json"> {cases: [...]} (see report.py). */
(function () {
  "use strict";
  var body = document.body;
  var errorCount = 0;
  function noteError() { errorCount += 1; body.setAttribute("data-js-errors", String(errorCount)); }
  window.addEventListener("error", noteError);
  window.addEventListener("unhandledrejection", noteError);
  if (window.console && console.error) {
    var consoleError = console.error;
    console.error = function () { noteError(); return consoleError.apply(console, arguments); };
  }
  var facesRendered = 0;

  var VIRIDIS = [[68, 1, 84], [65, 68, 135], [42, 120, 142], [34, 168, 132], [122, 209, 81], [253, 231, 37]];
  var SKIN = [214, 188, 170];
  var YAW = 0.35, PITCH = 0.12;

  function colormap(t) {
    if (!(t >= 0)) t = 0;
    if (t > 1) t = 1;
    var x = t * (VIRIDIS.length - 1), i = Math.min(Math.floor(x), VIRIDIS.length - 2), f = x - i;
    var a = VIRIDIS[i], b = VIRIDIS[i + 1];
    return [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])];
  }

  function bytes(b64) {
    var bin = atob(b64), out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  /* int16 frames -> Float32Array (F * N * 3), NaN where missing */
  function decodeSeq(seq) {
    if (seq._pos) return seq._pos;
    var q = new Int16Array(bytes(seq.q).buffer), pos = new Float32Array(q.length);
    for (var i = 0; i < q.length; i++) {
      var c = i % 3;
      pos[i] = q[i] === -32768 ? NaN : seq.lo[c] + (q[i] + 32767) * seq.step[c];
    }
    seq._pos = pos;
    return pos;
  }
  function decodeTris(mesh) {
    if (!mesh._tri) mesh._tri = new Uint32Array(bytes(mesh.tri).buffer);
    return mesh._tri;
  }

  function rotate(x, y, z) {
    var cy = Math.cos(YAW), sy = Math.sin(YAW), cp = Math.cos(PITCH), sp = Math.sin(PITCH);
    var x1 = cy * x + sy * z, z1 = -sy * x + cy * z;
    return [x1, cp * y - sp * z1, sp * y + cp * z1];
  }

  /* camera from the first frame of pos (n points): centre and scale of the rotated bbox */
  function makeCamera(pos, n, w, h) {
    var lo = [Infinity, Infinity], hi = [-Infinity, -Infinity], c = [0, 0, 0], k = 0;
    for (var i = 0; i < n; i++) {
      var x = pos[3 * i], y = pos[3 * i + 1], z = pos[3 * i + 2];
      if (isNaN(x)) continue;
      c[0] += x; c[1] += y; c[2] += z; k++;
    }
    if (!k) return null;
    c = [c[0] / k, c[1] / k, c[2] / k];
    for (i = 0; i < n; i++) {
      if (isNaN(pos[3 * i])) continue;
      var r = rotate(pos[3 * i] - c[0], pos[3 * i + 1] - c[1], pos[3 * i + 2] - c[2]);
      lo[0] = Math.min(lo[0], r[0]); lo[1] = Math.min(lo[1], r[1]);
      hi[0] = Math.max(hi[0], r[0]); hi[1] = Math.max(hi[1], r[1]);
    }
    var s = 0.86 * Math.min(w / Math.max(hi[0] - lo[0], 1e-9), h / Math.max(hi[1] - lo[1], 1e-9));
    return { c: c, s: s, ox: w / 2 - s * (lo[0] + hi[0]) / 2, oy: h / 2 + s * (lo[1] + hi[1]) / 2 };
  }

  function project(pos, offset, n, cam) {
    var out = new Float32Array(3 * n);
    for (var i = 0; i < n; i++) {
      var j = offset + 3 * i;
      var r = rotate(pos[j] - cam.c[0], pos[j + 1] - cam.c[1], pos[j + 2] - cam.c[2]);
      out[3 * i] = cam.ox + cam.s * r[0];
      out[3 * i + 1] = cam.oy - cam.s * r[1];
      out[3 * i + 2] = r[2];
    }
    return out;
  }

  /* Painter's algorithm with flat Lambert shading; colors: per-vertex [r,g,b] array or null */
  function drawMesh(canvas, pos, offset, n, tri, cam, colors) {
    var ctx = canvas.getContext("2d");
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!cam) return;
    var p = project(pos, offset, n, cam), nt = tri.length / 3, order = [], depth = new Float32Array(nt);
    for (var t = 0; t < nt; t++) {
      var a = tri[3 * t], b = tri[3 * t + 1], c = tri[3 * t + 2];
      depth[t] = p[3 * a + 2] + p[3 * b + 2] + p[3 * c + 2];
      if (!isNaN(depth[t])) order.push(t);
    }
    order.sort(function (i, j) { return depth[i] - depth[j]; });
    var L = [0.35, 0.45, 0.82], ln = Math.sqrt(L[0] * L[0] + L[1] * L[1] + L[2] * L[2]);
    for (var k = 0; k < order.length; k++) {
      t = order[k];
      a = tri[3 * t]; b = tri[3 * t + 1]; c = tri[3 * t + 2];
      var ux = p[3 * b] - p[3 * a], uy = -(p[3 * b + 1] - p[3 * a + 1]), uz = p[3 * b + 2] - p[3 * a + 2];
      var vx = p[3 * c] - p[3 * a], vy = -(p[3 * c + 1] - p[3 * a + 1]), vz = p[3 * c + 2] - p[3 * a + 2];
      var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      var nn = Math.sqrt(nx * nx + ny * ny + nz * nz) || 1;
      var shade = 0.3 + 0.7 * Math.abs((nx * L[0] + ny * L[1] + nz * L[2]) / (nn * ln));
      var col = SKIN;
      if (colors) {
        var ca = colors[a], cb = colors[b], cc = colors[c];
        col = [(ca[0] + cb[0] + cc[0]) / 3, (ca[1] + cb[1] + cc[1]) / 3, (ca[2] + cb[2] + cc[2]) / 3];
      }
      var fill = "rgb(" + Math.round(col[0] * shade) + "," + Math.round(col[1] * shade) + "," + Math.round(col[2] * shade) + ")";
      ctx.fillStyle = fill;
      ctx.strokeStyle = fill;
      ctx.lineWidth = 0.6;
      ctx.beginPath();
      ctx.moveTo(p[3 * a], p[3 * a + 1]);
      ctx.lineTo(p[3 * b], p[3 * b + 1]);
      ctx.lineTo(p[3 * c], p[3 * c + 1]);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
    }
    if (order.length) { facesRendered += 1; body.setAttribute("data-faces-rendered", String(facesRendered)); }
  }

  function drawPoints(canvas, pos, offset, n, cam) {
    var ctx = canvas.getContext("2d");
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!cam) return;
    var p = project(pos, offset, n, cam);
    ctx.fillStyle = "#1f5f99";
    for (var i = 0; i < n; i++) {
      if (isNaN(p[3 * i])) continue;
      ctx.beginPath();
      ctx.arc(p[3 * i], p[3 * i + 1], 3, 0, 2 * Math.PI);
      ctx.fill();
    }
  }

  function element(tag, cls, text) {
    var e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function cell(label, w, h) {
    var d = element("div", "cell"), cv = element("canvas");
    cv.width = w; cv.height = h;
    d.appendChild(cv);
    d.appendChild(element("div", "label", label));
    d.title = label;
    return { div: d, canvas: cv };
  }

  /* One case: decoded sequences and drawing of panel k at embedded frame f */
  function CaseView(data) {
    this.data = data;
    this.nf = data.frames.length;
    this.nv = data.mesh.nv;
    this.tri = decodeTris(data.mesh);
    this.truth = null;
    var self = this;
    data.seqs.forEach(function (s) { if (s.kind === "truth") self.truth = s; });
    this.panels = [];
    var src = data.source;
    if (src.q) {
      this.panels.push({ label: "source (" + src.kind + ")", kind: "source", seq: src, n: src.mesh ? src.mesh.nv : decodeSeq(src).length / 3 / this.nf, tri: src.mesh ? decodeTris(src.mesh) : null });
    }
    data.seqs.forEach(function (s) { self.panels.push({ label: s.label, kind: s.kind, seq: s, n: self.nv, tri: self.tri }); });
    this.cams = {};
  }
  /* one camera per kind of panel and canvas size, so that all target panels share a view */
  CaseView.prototype.camera = function (panel, w, h) {
    var group = panel.kind === "source" || panel.kind === "neutral" ? panel.kind : "target";
    var key = group + w + "x" + h;
    if (!(key in this.cams)) {
      var ref = group === "target" ? (this.truth || panel.seq) : panel.seq;
      this.cams[key] = makeCamera(decodeSeq(ref), panel.n, w, h);
    }
    return this.cams[key];
  };
  CaseView.prototype.errorColors = function (panel, f) {
    if (!this.truth || panel.kind !== "method") return null;
    var a = decodeSeq(panel.seq), b = decodeSeq(this.truth), off = 3 * this.nv * f, out = new Array(this.nv);
    for (var i = 0; i < this.nv; i++) {
      var dx = a[off + 3 * i] - b[off + 3 * i], dy = a[off + 3 * i + 1] - b[off + 3 * i + 1], dz = a[off + 3 * i + 2] - b[off + 3 * i + 2];
      out[i] = colormap(100 * Math.sqrt(dx * dx + dy * dy + dz * dz) / this.data.height / this.data.heatMax);
    }
    return out;
  };
  CaseView.prototype.draw = function (panel, canvas, f, mode) {
    var pos = decodeSeq(panel.seq), cam = this.camera(panel, canvas.width, canvas.height), off = 3 * panel.n * f;
    if (!panel.tri) { drawPoints(canvas, pos, off, panel.n, cam); return; }
    drawMesh(canvas, pos, off, panel.n, panel.tri, cam, mode === "error" ? this.errorColors(panel, f) : null);
  };

  function buildViewer(root, view) {
    var controls = element("div", "controls"), play = element("button", null, "play");
    var slider = element("input"), label = element("span"), mode = element("select");
    slider.type = "range"; slider.min = 0; slider.max = view.nf - 1; slider.value = 0;
    [["shaded", "shaded"], ["error", "coloured by error vs truth"]].forEach(function (o) {
      var opt = element("option", null, o[1]); opt.value = o[0]; mode.appendChild(opt);
    });
    controls.appendChild(play); controls.appendChild(slider); controls.appendChild(label); controls.appendChild(mode);
    root.appendChild(controls);
    var grid = element("div", "grid"), cells = [];
    view.panels.forEach(function (p) { var c = cell(p.label, 210, 245); cells.push(c); grid.appendChild(c.div); });
    root.appendChild(grid);
    function render() {
      var f = Number(slider.value);
      label.textContent = "frame " + view.data.frames[f] + " (" + (f + 1) + "/" + view.nf + " embedded)";
      view.panels.forEach(function (p, k) { view.draw(p, cells[k].canvas, f, mode.value); });
    }
    var timer = null;
    play.addEventListener("click", function () {
      if (timer) { clearInterval(timer); timer = null; play.textContent = "play"; return; }
      play.textContent = "pause";
      timer = setInterval(function () { slider.value = (Number(slider.value) + 1) % view.nf; render(); }, 150);
    });
    slider.addEventListener("input", render);
    mode.addEventListener("change", render);
    if (view.data.keyFrames.length) slider.value = view.data.keyFrames[0];
    render();
  }

  function buildKeyFrames(root, view) {
    if (!view.data.keyFrames.length) { root.appendChild(element("p", "note", "no ground truth: no key frames")); return; }
    var table = element("table", "keys"), head = element("tr");
    /* one column per panel, all within the section's width (a 1280 px window leaves about 1150 px) */
    var avail = Math.max(root.clientWidth || 1150, 400) - 70;
    var w = Math.max(40, Math.min(150, Math.floor(avail / view.panels.length) - 6)), h = Math.round(w * 7 / 6);
    head.appendChild(element("th", null, ""));
    view.panels.forEach(function (p) { var th = element("th", null, p.label); th.style.maxWidth = (w + 4) + "px"; head.appendChild(th); });
    table.appendChild(head);
    view.data.keyFrames.forEach(function (f) {
      var tr = element("tr");
      tr.appendChild(element("th", null, "frame " + view.data.frames[f]));
      view.panels.forEach(function (p) {
        var td = element("td"), cv = element("canvas");
        cv.width = w; cv.height = h;
        td.appendChild(cv); tr.appendChild(td);
        view.draw(p, cv, f, "shaded");
      });
      table.appendChild(tr);
    });
    root.appendChild(table);
  }

  function buildHeat(root, view) {
    var data = view.data;
    if (!data.heat.length) { root.appendChild(element("p", "note", "no ground truth or no successful run: no error maps")); return; }
    var panel = { kind: "neutral", seq: data.neutral, n: view.nv }, neutral = decodeSeq(data.neutral);
    var bar = element("div", "colorbar");
    bar.appendChild(element("span", null, "0"));
    bar.appendChild(element("span", "bar"));
    bar.appendChild(element("span", null, data.heatMax.toPrecision(3) + " % face height"));
    root.appendChild(bar);
    var grid = element("div", "grid");
    data.heat.forEach(function (h) {
      var c = cell(h.label, 220, 255), q = bytes(h.q), colors = new Array(q.length);
      for (var i = 0; i < q.length; i++) colors[i] = colormap(q[i] / 255);
      drawMesh(c.canvas, neutral, 0, view.nv, view.tri, view.camera(panel, 220, 255), colors);
      grid.appendChild(c.div);
    });
    root.appendChild(grid);
  }

  function main() {
    var node = document.getElementById("report-data");
    if (!node) return;
    var data = JSON.parse(node.textContent);
    var views = data.cases.map(function (c) { return new CaseView(c); });
    function each(selector, fn) {
      var nodes = document.querySelectorAll(selector);
      for (var i = 0; i < nodes.length; i++) {
        var view = views[Number(nodes[i].getAttribute("data-case"))];
        if (view) fn(nodes[i], view);
      }
    }
    each(".viewer", buildViewer);
    each(".keyframes", buildKeyFrames);
    each(".heat", buildHeat);
    body.setAttribute("data-report-ready", "1");
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", main);
  else main();
})();
