// faceretarget studio: the page. Talks to the studio's JSON API (docs/studio.md) with the
// token of its own URL; draws with the vendored three.js. `window.studio` exposes the state
// (the tests read it).
import * as THREE from './vendor/three.module.js';
import { OrbitControls } from './vendor/OrbitControls.js';

const token = new URLSearchParams(location.search).get('token') || '';
const $ = (id) => document.getElementById(id);

const state = {
  ready: false, busy: 0, session: null, method: null, result: null, frame: 0, playing: false,
  weights: null, headMotion: null, targetFrames: null, sourceFrames: null, errors: null,
  heat: false, heatMax: 5, focus: null, rigs: {}, picked: null, live: false, liveSeq: 0,
  lastError: '', lastExport: '', curvesVersion: 0,
};
window.studio = state;

// ---- the API -------------------------------------------------------------------------------
class ApiError extends Error {}

async function api(path, { method = 'GET', body, binary = false } = {}) {
  const headers = { 'X-Studio-Token': token };
  if (body !== undefined) headers['Content-Type'] = 'application/json';
  const res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!res.ok) {
    let message = `${res.status} ${res.statusText}`;
    try { message = (await res.json()).message || message; } catch (e) { /* not JSON */ }
    throw new ApiError(message);
  }
  return binary ? new Float32Array(await res.arrayBuffer()) : res.json();
}

function f32(text) {
  const bin = atob(text);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Float32Array(bytes.buffer);
}

function u32(text) {
  const bin = atob(text);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Uint32Array(bytes.buffer);
}

// frames [start, stop) of an (F, per) float32 resource, asked in pieces of at most ~16 MB
async function framesOf(url, start, stop, per, into) {
  const step = Math.max(1, Math.floor(16e6 / (per * 4)));
  for (let a = start; a < stop; a += step) {
    const b = Math.min(stop, a + step);
    const part = await api(`${url}${url.includes('?') ? '&' : '?'}start=${a}&stop=${b}`, { binary: true });
    into.set(part, a * per);
  }
  return into;
}

async function busy(label, work) {
  state.busy++;
  status(label + '…');
  try {
    return await work();
  } catch (err) {
    showError(err.message || String(err));
    return null;
  } finally {
    state.busy--;
  }
}

function status(text) { $('status').textContent = text; }
function showError(text) {
  state.lastError = text;
  $('error-text').textContent = text;
  $('error').hidden = false;
  status('error');
}
$('error-close').onclick = () => { $('error').hidden = true; };

// ---- the 3D views ---------------------------------------------------------------------------
class View {
  constructor(el) {
    this.el = el;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
    el.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0xf7f8fa);
    this.camera = new THREE.PerspectiveCamera(30, 1, 0.01, 1e5);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x667080, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(0.4, 0.6, 1);
    this.camera.add(sun);
    this.scene.add(this.camera);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener('change', () => this.render());
    this.object = null;
    new ResizeObserver(() => this.resize()).observe(el);
  }
  resize() {
    const w = this.el.clientWidth || 1, h = this.el.clientHeight || 1;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }
  show(object, framing) {
    if (this.object) {
      this.scene.remove(this.object);
      this.object.geometry.dispose();
    }
    this.object = object;
    this.scene.add(object);
    if (framing && !this.framed) {
      this.framed = true;
      const sphere = framing.boundingSphere || (framing.computeBoundingSphere(), framing.boundingSphere);
      const d = sphere.radius / Math.sin((this.camera.fov * Math.PI) / 360) * 1.05;
      this.controls.target.copy(sphere.center);
      this.camera.position.copy(sphere.center).add(new THREE.Vector3(0, 0, d));
      this.camera.near = d / 100; this.camera.far = d * 100;
      this.camera.updateProjectionMatrix();
      this.controls.update();
    }
    this.render();
  }
  render() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.renderer.render(this.scene, this.camera); });
  }
}

const views = { source: new View($('view-source')), target: new View($('view-target')) };
const SKIN = new THREE.Color(0xd9b8a3);

function meshOf(positions, triangles, colors = false) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  geometry.setIndex(new THREE.BufferAttribute(triangles, 1));
  if (colors) {
    const c = new Float32Array(positions.length);
    for (let i = 0; i < c.length; i += 3) { c[i] = SKIN.r; c[i + 1] = SKIN.g; c[i + 2] = SKIN.b; }
    geometry.setAttribute('color', new THREE.BufferAttribute(c, 3));
  }
  geometry.computeVertexNormals();
  const material = new THREE.MeshStandardMaterial({
    color: colors ? 0xffffff : SKIN, vertexColors: colors, roughness: 0.75, side: THREE.DoubleSide,
  });
  return new THREE.Mesh(geometry, material);
}

function pointsOf(positions) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  const points = new THREE.Points(geometry, new THREE.PointsMaterial({ color: 0x2b6cb0, size: 6, sizeAttenuation: false }));
  points.frustumCulled = false;
  return points;
}

// ---- loading the session ---------------------------------------------------------------------
async function start() {
  const s = await api('/api/session');
  state.session = s;
  $('case-name').textContent = s.name;
  $('source-caption').textContent = `${s.source.kind}, ${s.source.n_frames} frames at ${s.source.fps} fps`;
  $('frame').max = s.source.n_frames - 1;
  $('heatmap').disabled = !s.truth;
  $('heatmap').title = s.truth ? 'distance to the known answer' : 'these inputs have no known answer';
  for (const f of s.files) {
    const li = document.createElement('li');
    const a = document.createElement('a');
    a.href = `/api/file?path=${encodeURIComponent(f.path)}&token=${encodeURIComponent(token)}`;
    a.textContent = f.name;
    a.title = f.path;
    li.append(a, ` (${(f.bytes / 1024).toFixed(0)} KB)`);
    $('files').append(li);
  }
  if (!s.files.length) $('files').innerHTML = '<li class="hint">a built-in case (no files)</li>';
  const select = $('method');
  for (const m of s.methods) {
    if (m.applies) {
      const o = document.createElement('option');
      o.value = m.name; o.textContent = m.name; o.title = m.summary;
      select.append(o);
    } else {
      const li = document.createElement('li');
      li.innerHTML = `<b></b>: <span></span>`;
      li.querySelector('b').textContent = m.name;
      li.querySelector('span').textContent = m.why_not;
      $('na-list').append(li);
    }
  }
  // the performance
  const per = s.source.n_points * 3;
  state.sourceFrames = await framesOf('/api/source', 0, s.source.n_frames, per, new Float32Array(s.source.n_frames * per));
  const first = state.sourceFrames.slice(0, per);
  const srcObject = s.source.triangles ? meshOf(first, u32(s.source.triangles)) : pointsOf(first);
  if (!s.source.triangles) srcObject.geometry.computeBoundingSphere();
  views.source.show(srcObject, srcObject.geometry);
  state.targetNeutral = f32(s.target.neutral);
  state.targetTriangles = u32(s.target.triangles);
  if (s.live) { $('live-panel').hidden = false; liveInfo(s.live); }
  const method = s.default_method || (select.options[0] && select.options[0].value);
  if (method) {
    select.value = method;
    buildParams(method, s.default_params || {});
    await runMethod();
  } else {
    showError('no registered method applies to these inputs; see "Methods that do not apply"');
  }
  state.ready = true;
}

// ---- the parameter panel, from the manifest ---------------------------------------------------
function buildParams(name, given = {}) {
  const m = state.session.methods.find((x) => x.name === name);
  state.method = m;
  $('params-method').textContent = name;
  const form = $('params');
  form.innerHTML = '';
  for (const p of m.parameters) {
    const label = document.createElement('label');
    label.className = 'param';
    label.title = `${p.doc}${p.valid ? `\nvalid: ${p.valid}` : ''}`;
    const title = document.createElement('span');
    title.textContent = p.name;
    label.append(title);
    const value = p.name in given ? given[p.name] : p.default;
    let input;
    if (p.widget === 'checkbox') {
      input = document.createElement('input'); input.type = 'checkbox'; input.checked = !!value;
    } else if (p.widget === 'select') {
      input = document.createElement('select');
      for (const c of p.choices) { const o = document.createElement('option'); o.value = o.textContent = c; input.append(o); }
      if (p.nullable) { const o = document.createElement('option'); o.value = ''; o.textContent = '(none)'; input.append(o); }
      input.value = value === null ? '' : value;
    } else if (p.widget === 'number') {
      input = document.createElement('input'); input.type = 'number';
      if (p.min !== null) input.min = p.min;
      if (p.max !== null) input.max = p.max;
      input.step = p.step;
      input.value = value === null ? '' : value;
    } else if (p.widget === 'text') {
      input = document.createElement('input'); input.type = 'text';
      input.value = value === null ? '' : value;
      if (p.choices && p.choices.length) input.placeholder = p.choices.join(' | ');
    } else {
      input = document.createElement('textarea');
      input.value = value === null ? '' : JSON.stringify(value);
      input.placeholder = 'JSON (empty: default)';
    }
    input.name = p.name;
    input.dataset.widget = p.widget;
    label.append(input);
    form.append(label);
  }
}

function paramValues() {
  const out = {};
  for (const p of state.method.parameters) {
    const input = $('params').elements[p.name];
    let v;
    if (p.widget === 'checkbox') v = input.checked;
    else if (p.widget === 'number') v = input.value === '' ? null : Number(input.value);
    else if (p.widget === 'select') v = input.value === '' ? null : input.value;
    else if (p.widget === 'text') v = input.value.trim() === '' ? null : (isFinite(Number(input.value)) ? Number(input.value) : input.value.trim());
    else {
      const t = input.value.trim();
      if (t === '') v = null;
      else { try { v = JSON.parse(t); } catch (e) { v = t; } }
    }
    if (JSON.stringify(v) !== JSON.stringify(p.default)) out[p.name] = v;
  }
  return out;
}

$('method').onchange = () => { buildParams($('method').value); runMethod(); };
$('run').onclick = () => runMethod();

async function runMethod() {
  const name = $('method').value;
  await busy(`running ${name}`, async () => {
    const sum = await api('/api/run', { method: 'POST', body: { method: name, params: paramValues() } });
    await applyResult(sum, true);
    const t = sum.seconds;
    status(`${sum.method}: ${sum.cached ? 'cached' : `fit ${t.fit.toFixed(2)} s, retarget ${t.retarget.toFixed(2)} s`}`);
  });
}

// ---- results ----------------------------------------------------------------------------------
async function applyResult(sum, fresh) {
  const previous = state.result;
  state.result = sum;
  const F = sum.n_frames, V = sum.n_vertices;
  const changed = fresh || !previous || previous.id !== sum.id ? [0, F - 1] : sum.changed;
  $('target-caption').textContent = `${sum.method}${sum.undo ? ` (${sum.undo} edits)` : ''}`;
  state.weights = sum.weights ? f32(sum.weights) : null;
  state.headMotion = sum.head_motion ? f32(sum.head_motion) : null;
  if (sum.outputs === 'weights') {
    if (!state.rigs[sum.rig]) state.rigs[sum.rig] = await api(`/api/rig/${sum.rig}`, { binary: true });
    state.targetFrames = null;
    if (fresh || !previous || previous.rig !== sum.rig || previous.outputs !== 'weights') buildMorphTarget(state.rigs[sum.rig], sum.weight_names.length);
  } else {
    if (fresh || !state.targetFrames || state.targetFrames.length !== F * V * 3) state.targetFrames = new Float32Array(F * V * 3);
    if (changed) await framesOf(`/api/result/vertices?id=${sum.id}`, changed[0], changed[1] + 1, V * 3, state.targetFrames);
    if (fresh || !previous || previous.outputs !== 'vertices') {
      const object = meshOf(state.targetFrames.slice(0, V * 3), state.targetTriangles, true);
      views.target.show(object, meshOf(state.targetNeutral, state.targetTriangles).geometry);
    }
  }
  if (state.heat) await loadErrors(fresh ? [0, F - 1] : changed);
  else state.errors = null;
  buildEditPanel();
  $('undo').disabled = !sum.undo;
  $('redo').disabled = !sum.redo;
  state.curvesVersion++;
  showFrame(state.frame);
}

function buildMorphTarget(stacked, M) {
  const V = state.session.target.n_vertices, n = V * 3;
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(stacked.slice(0, n), 3));
  geometry.setIndex(new THREE.BufferAttribute(state.targetTriangles, 1));
  geometry.morphAttributes.position = [];
  for (let m = 0; m < M; m++) geometry.morphAttributes.position.push(new THREE.BufferAttribute(stacked.slice((m + 1) * n, (m + 2) * n), 3));
  geometry.morphTargetsRelative = true;
  const c = new Float32Array(n);
  for (let i = 0; i < n; i += 3) { c[i] = SKIN.r; c[i + 1] = SKIN.g; c[i + 2] = SKIN.b; }
  geometry.setAttribute('color', new THREE.BufferAttribute(c, 3));
  geometry.computeVertexNormals();
  const mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.75, side: THREE.DoubleSide }));
  mesh.updateMorphTargets();
  mesh.matrixAutoUpdate = false;
  views.target.show(mesh, meshOf(state.targetNeutral, state.targetTriangles).geometry);
}

async function loadErrors(range) {
  const sum = state.result, F = sum.n_frames, V = sum.n_vertices;
  if (!state.errors || state.errors.length !== F * V) { state.errors = new Float32Array(F * V); range = [0, F - 1]; }
  if (range) await framesOf(`/api/result/error?id=${sum.id}`, range[0], range[1] + 1, V, state.errors);
  // colour scale: the 99th percentile of (a sample of) the errors, rounded up to 1, 2 or 5
  const sample = [];
  for (let i = 0; i < state.errors.length; i += Math.max(1, Math.floor(state.errors.length / 20000))) sample.push(state.errors[i]);
  sample.sort((a, b) => a - b);
  const p99 = sample[Math.floor(0.99 * (sample.length - 1))] || 1;
  const decade = Math.pow(10, Math.floor(Math.log10(p99)));
  state.heatMax = Number(([1, 2, 5, 10].find((k) => k * decade >= p99) * decade).toPrecision(2));
}

// ---- one frame on screen -----------------------------------------------------------------------
function showFrame(f) {
  const s = state.session, sum = state.result;
  state.frame = f = Math.max(0, Math.min(s.source.n_frames - 1, f | 0));
  $('frame').value = f;
  $('frame-label').textContent = f;
  $('edit-frame').textContent = `frame ${f}`;
  if (!state.playing) {  // the edit window follows the frame until the user sets it
    const a = $('win-a'), b = $('win-b'), n = s.source.n_frames;
    if (!state.windowSet || Number(a.value) > f || Number(b.value) < f) {
      a.value = Math.max(0, f - 30);
      b.value = Math.min(n - 1, f + 30);
      state.windowSet = false;
    }
  }
  if (!state.live) {
    const per = s.source.n_points * 3;
    const src = views.source.object;
    src.geometry.attributes.position.array.set(state.sourceFrames.subarray(f * per, (f + 1) * per));
    src.geometry.attributes.position.needsUpdate = true;
    if (src.isMesh) src.geometry.computeVertexNormals();
    views.source.render();
  }
  if (sum && !state.live) {
    const obj = views.target.object, V = sum.n_vertices;
    if (sum.outputs === 'weights') {
      const M = sum.weight_names.length;
      for (let m = 0; m < M; m++) obj.morphTargetInfluences[m] = state.weights[f * M + m];
      if (state.headMotion) obj.matrix.set(...state.headMotion.subarray(f * 16, f * 16 + 16));
      else obj.matrix.identity();
      obj.matrixWorldNeedsUpdate = true;
    } else {
      obj.geometry.attributes.position.array.set(state.targetFrames.subarray(f * V * 3, (f + 1) * V * 3));
      obj.geometry.attributes.position.needsUpdate = true;
      obj.geometry.computeVertexNormals();
    }
    paintTarget();
    views.target.render();
    if (!state.playing) updateSliders();
  }
  drawCurves();
}

function heatColor(t, out, i) {  // blue - grey - red
  t = Math.max(0, Math.min(1, t));
  const a = [0.23, 0.3, 0.75], b = [0.87, 0.87, 0.87], c = [0.71, 0.02, 0.15];
  const [p, q, u] = t < 0.5 ? [a, b, t * 2] : [b, c, t * 2 - 1];
  for (let k = 0; k < 3; k++) out[i + k] = p[k] + (q[k] - p[k]) * u;
}

function paintTarget() {
  const obj = views.target.object, sum = state.result;
  if (!obj || !obj.geometry.attributes.color) return;
  const colors = obj.geometry.attributes.color.array, V = sum.n_vertices, f = state.frame;
  const region = state.picked ? new Set(state.picked.region) : null;
  for (let v = 0; v < V; v++) {
    if (state.heat && state.errors) heatColor(state.errors[f * V + v] / state.heatMax, colors, v * 3);
    else { colors[v * 3] = SKIN.r; colors[v * 3 + 1] = SKIN.g; colors[v * 3 + 2] = SKIN.b; }
    if (region && region.has(v)) { colors[v * 3] = 0.2; colors[v * 3 + 1] = 0.6; colors[v * 3 + 2] = 0.3; }
  }
  obj.geometry.attributes.color.needsUpdate = true;
  $('heat-legend').hidden = !state.heat;
  $('heat-max').textContent = state.heatMax;
}

$('frame').oninput = () => showFrame(Number($('frame').value));
$('heatmap').onchange = async () => {
  state.heat = $('heatmap').checked;
  if (state.heat && !state.errors) await busy('computing the error', () => loadErrors([0, state.result.n_frames - 1]));
  status(state.heat ? 'heat map: distance to the known answer' : '');
  showFrame(state.frame);
};

$('play').onclick = () => {
  state.playing = !state.playing;
  $('play').textContent = state.playing ? '❚❚' : '▶';
  if (!state.playing) { showFrame(state.frame); return; }
  const fps = state.session.source.fps, F = state.session.source.n_frames;
  const t0 = performance.now(), f0 = state.frame;
  const tick = (now) => {
    if (!state.playing) return;
    showFrame((f0 + Math.floor(((now - t0) / 1000) * fps)) % F);
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
};

// ---- the weight curves -------------------------------------------------------------------------
function drawCurves() {
  const canvas = $('curves'), ctx = canvas.getContext('2d');
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== w) canvas.width = w;
  ctx.clearRect(0, 0, w, h);
  const sum = state.result;
  const F = state.session.source.n_frames;
  const x = (f) => 30 + ((w - 40) * f) / Math.max(1, F - 1);
  if (sum && !state.weights && state.heat && state.errors) {  // mean error per frame
    const V = sum.n_vertices, mean = new Float32Array(F);
    let hi = 1e-9;
    for (let f = 0; f < F; f++) {
      let t = 0;
      for (let v = 0; v < V; v++) t += state.errors[f * V + v];
      mean[f] = t / V; hi = Math.max(hi, mean[f]);
    }
    const y = (v) => h - 14 - ((h - 24) * v) / hi;
    ctx.strokeStyle = '#b40426'; ctx.lineWidth = 1.5; ctx.beginPath();
    for (let f = 0; f < F; f++) { if (f) ctx.lineTo(x(f), y(mean[f])); else ctx.moveTo(x(f), y(mean[f])); }
    ctx.stroke();
    ctx.fillStyle = '#b40426';
    ctx.fillText(`mean error per frame (max ${hi.toPrecision(2)} % of face height)`, 34, 12);
  } else if (!sum || !state.weights) {
    ctx.fillStyle = '#6b7585';
    ctx.fillText(sum ? `${sum.method} gives vertices, not weight curves (the heat map plots its error here)` : '', 30, 20);
  } else {
    const M = sum.weight_names.length, W = state.weights;
    let lo = 0, hi = 1;
    for (let i = 0; i < W.length; i++) { if (W[i] < lo) lo = W[i]; if (W[i] > hi) hi = W[i]; }
    const y = (v) => h - 14 - ((h - 24) * (v - lo)) / (hi - lo);
    ctx.strokeStyle = '#e3e6ea';
    ctx.beginPath(); ctx.moveTo(30, y(0)); ctx.lineTo(w - 10, y(0)); ctx.moveTo(30, y(1)); ctx.lineTo(w - 10, y(1)); ctx.stroke();
    ctx.fillStyle = '#6b7585';
    ctx.fillText('0', 12, y(0) + 4); ctx.fillText('1', 12, y(1) + 4);
    const focus = state.focus === null ? -1 : sum.weight_names.indexOf(state.focus);
    for (let m = 0; m < M; m++) {
      ctx.strokeStyle = m === focus ? '#c0392b' : `hsla(${(m * 137) % 360}, 55%, 45%, 0.45)`;
      ctx.lineWidth = m === focus ? 2.2 : 1;
      ctx.beginPath();
      for (let f = 0; f < F; f++) { const v = W[f * M + m]; if (f) ctx.lineTo(x(f), y(v)); else ctx.moveTo(x(f), y(v)); }
      ctx.stroke();
    }
    if (focus >= 0) { ctx.fillStyle = '#c0392b'; ctx.fillText(state.focus, 34, 12); }
  }
  const win = editWindow();
  if (win && sum && sum.edit.length) {
    ctx.fillStyle = 'rgba(43,108,176,0.08)';
    ctx.fillRect(x(win[0]), 0, x(win[1]) - x(win[0]), h);
  }
  ctx.strokeStyle = '#1d2430'; ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(x(state.frame), 0); ctx.lineTo(x(state.frame), h); ctx.stroke();
}

function frameAt(event) {
  const canvas = $('curves'), r = canvas.getBoundingClientRect();
  const F = state.session.source.n_frames;
  return Math.round(((event.clientX - r.left - 30) / Math.max(1, r.width - 40)) * (F - 1));
}
$('curves').onpointerdown = (e) => {
  showFrame(frameAt(e));
  $('curves').onpointermove = (ev) => showFrame(frameAt(ev));
};
window.addEventListener('pointerup', () => { $('curves').onpointermove = null; });
window.addEventListener('resize', () => drawCurves());

// ---- editing -------------------------------------------------------------------------------------
function editWindow() {
  const sum = state.result;
  if (!sum || !sum.edit_window || $('win-default').checked) return null;
  const F = sum.n_frames;
  let a = Number($('win-a').value), b = Number($('win-b').value);
  if ($('win-a').value === '' || !(a <= state.frame)) a = Math.max(0, state.frame - 30);
  if ($('win-b').value === '' || !(b >= state.frame)) b = Math.min(F - 1, state.frame + 30);
  return [a, b];
}

function buildEditPanel() {
  const kinds = state.result.edit;
  $('edit-none').hidden = kinds.length > 0;
  $('edit-window').hidden = !kinds.length || !state.result.edit_window;
  $('edit-weights').hidden = !kinds.includes('weights');
  $('edit-points').hidden = !kinds.includes('points');
  $('edit-detail').hidden = !kinds.includes('detail');
  if (kinds.includes('weights')) buildSliders();
}

function buildSliders() {
  const sum = state.result, box = $('sliders');
  if (box.dataset.for === sum.id && box.children.length) return;
  box.dataset.for = sum.id;
  box.innerHTML = '';
  sum.weight_names.forEach((name, m) => {
    const row = document.createElement('label');
    row.className = 'slider';
    row.dataset.shape = name;
    const span = document.createElement('span'); span.textContent = name; span.title = name;
    const input = document.createElement('input');
    input.type = 'range'; input.min = -0.5; input.max = 1.5; input.step = 0.01; input.name = name;
    const out = document.createElement('output');
    input.oninput = () => { out.textContent = Number(input.value).toFixed(2); state.focus = name; drawCurves(); };
    input.onchange = () => editWeights({ [name]: Number(input.value) });
    input.onfocus = () => { state.focus = name; drawCurves(); };
    row.append(span, input, out);
    box.append(row);
  });
  filterSliders();
}

function updateSliders() {
  const sum = state.result;
  if (!sum || !state.weights || !sum.edit.includes('weights')) return;
  const M = sum.weight_names.length;
  for (const row of $('sliders').children) {
    const m = sum.weight_names.indexOf(row.dataset.shape);
    const v = state.weights[state.frame * M + m];
    row.querySelector('input').value = v;
    row.querySelector('output').textContent = v.toFixed(2);
  }
}

function filterSliders() {
  const q = $('weight-filter').value.toLowerCase();
  for (const row of $('sliders').children) row.hidden = q !== '' && !row.dataset.shape.toLowerCase().includes(q);
}
$('weight-filter').oninput = filterSliders;
$('win-a').oninput = $('win-b').oninput = () => { state.windowSet = true; drawCurves(); };
$('win-default').onchange = () => drawCurves();

async function edit(request, label) {
  const sum = state.result;
  await busy(label, async () => {
    const t0 = performance.now();
    const out = await api('/api/edit', { method: 'POST', body: { id: sum.id, frame: state.frame, window: editWindow(), ...request } });
    await applyResult(out, false);
    status(`${label}: frames ${out.changed ? out.changed.join('–') : 'none'} changed (${(performance.now() - t0).toFixed(0)} ms)`);
  });
}

function editWeights(weights) {
  return edit({ kind: 'weights', weights }, `edit of ${Object.keys(weights).join(', ')} at frame ${state.frame}`);
}

for (const [button, path] of [['undo', '/api/undo'], ['redo', '/api/redo']]) {
  $(button).onclick = () => busy(button, async () => {
    const out = await api(path, { method: 'POST', body: { id: state.result.id } });
    await applyResult(out, false);
    status(`${button} done`);
  });
}
window.addEventListener('keydown', (e) => {
  if (!(e.ctrlKey || e.metaKey) || e.target.tagName === 'INPUT' || e.target.tagName === 'TEXTAREA') return;
  if (e.key === 'z' && !$('undo').disabled) { e.preventDefault(); $('undo').click(); }
  if ((e.key === 'y' || (e.key === 'Z' && e.shiftKey)) && !$('redo').disabled) { e.preventDefault(); $('redo').click(); }
});

// picking on the target: the nearest vertex of the triangle under the pointer, in world space
const raycaster = new THREE.Raycaster();
function pick(event) {
  const view = views.target, r = view.renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((event.clientX - r.left) / r.width) * 2 - 1, -((event.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(ndc, view.camera);
  const hit = raycaster.intersectObject(view.object)[0];
  if (!hit) return null;
  const obj = view.object, p = new THREE.Vector3();
  let best = null;
  for (const v of [hit.face.a, hit.face.b, hit.face.c]) {
    obj.getVertexPosition(v, p);
    p.applyMatrix4(obj.matrixWorld);
    const d = p.distanceTo(hit.point);
    if (!best || d < best.d) best = { vertex: v, d, position: p.clone() };
  }
  return best;
}

const marker = new THREE.Mesh(new THREE.SphereGeometry(1, 12, 8), new THREE.MeshBasicMaterial({ color: 0x2b6cb0 }));
let drag = null;
views.target.renderer.domElement.addEventListener('pointerdown', (e) => {
  if (!state.result || state.live) return;
  if ($('drag-mode').checked && state.result.edit.includes('points')) {
    const p = pick(e);
    if (!p) return;
    views.target.controls.enabled = false;
    const normal = views.target.camera.getWorldDirection(new THREE.Vector3());
    drag = { ...p, plane: new THREE.Plane().setFromNormalAndCoplanarPoint(normal, p.position), to: p.position.clone() };
    marker.scale.setScalar(state.session.target.height / 120);
    marker.position.copy(p.position);
    views.target.scene.add(marker);
    views.target.render();
  } else if ($('pick-mode').checked && state.result.edit.includes('detail')) {
    const p = pick(e);
    if (!p) return;
    const radius = (Number($('detail-radius').value) / 100) * state.session.target.height;
    const obj = views.target.object, q = new THREE.Vector3(), region = [];
    for (let v = 0; v < state.result.n_vertices; v++) {
      obj.getVertexPosition(v, q); q.applyMatrix4(obj.matrixWorld);
      if (q.distanceTo(p.position) <= radius) region.push(v);
    }
    state.picked = { vertex: p.vertex, radius, region, frame: state.frame };
    $('detail-picked').textContent = `${region.length} vertices around vertex ${p.vertex} at frame ${state.frame}`;
    $('detail-apply').disabled = false;
    paintTarget();
    views.target.render();
  }
});
views.target.renderer.domElement.addEventListener('pointermove', (e) => {
  if (!drag) return;
  const view = views.target, r = view.renderer.domElement.getBoundingClientRect();
  raycaster.setFromCamera(new THREE.Vector2(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1), view.camera);
  if (raycaster.ray.intersectPlane(drag.plane, drag.to)) { marker.position.copy(drag.to); view.render(); }
});
window.addEventListener('pointerup', () => {
  if (!drag) return;
  const d = drag;
  drag = null;
  views.target.controls.enabled = true;
  views.target.scene.remove(marker);
  if (d.to.distanceTo(d.position) > 0) {
    edit({ kind: 'points', vertex: d.vertex, position: d.to.toArray() }, `move of vertex ${d.vertex} at frame ${state.frame}`);
  }
});
$('detail-apply').onclick = () => {
  const p = state.picked;
  if (!p) return;
  if (p.frame !== state.frame) showFrame(p.frame);
  state.picked = null;
  $('detail-apply').disabled = true;
  $('detail-picked').textContent = 'no region picked';
  edit({ kind: 'detail', vertex: p.vertex, radius: p.radius, operation: $('detail-op').value, factor: Number($('detail-factor').value) },
    `${$('detail-op').value} of the detail around vertex ${p.vertex}`);
};

// ---- export --------------------------------------------------------------------------------------
for (const fmt of ['glb', 'csv', 'pc2']) {
  $(`export-${fmt}`).onclick = () => busy(`exporting ${fmt}`, async () => {
    const out = await api('/api/export', { method: 'POST', body: { id: state.result.id, format: fmt } });
    state.lastExport = out.path;
    $('export-msg').textContent = `wrote ${out.path} (${(out.bytes / 1024).toFixed(0)} KB)`;
    status(`exported ${fmt}`);
  });
}

// ---- live ----------------------------------------------------------------------------------------
function liveInfo(info) {
  const lat = info.latency_ms;
  $('live-info').textContent = `${info.method} on udp://127.0.0.1:${info.port}: ${info.status}` +
    (info.frames ? `; ${info.frames} frames, latency ${lat.last.toFixed(1)} ms (median ${lat.median.toFixed(1)})` : '') +
    (info.dropped ? `; ${info.dropped} dropped` : '') + (info.error ? `; ${info.error}` : '');
}

$('live-on').onchange = async () => {
  state.live = $('live-on').checked;
  if (!state.live) { await applyResult(state.result, true); return; }
  const s = state.session;
  $('target-caption').textContent = `live: ${s.live.method}`;
  $('heat-legend').hidden = true;
  const target = meshOf(state.targetNeutral.slice(), state.targetTriangles);
  views.target.show(target, target.geometry);
  while (state.live) {
    let r;
    try { r = await api(`/api/live?after=${state.liveSeq}`); } catch (err) { showError(err.message); break; }
    liveInfo(r.info);
    if (!r.frame || !state.live) continue;
    state.liveSeq = r.frame.seq;
    const tgt = views.target.object;
    tgt.geometry.attributes.position.array.set(f32(r.frame.target));
    tgt.geometry.attributes.position.needsUpdate = true;
    tgt.geometry.computeVertexNormals();
    views.target.render();
    const src = views.source.object, pts = f32(r.frame.source);
    if (pts.length === src.geometry.attributes.position.array.length) {
      src.geometry.attributes.position.array.set(pts);
      src.geometry.attributes.position.needsUpdate = true;
      if (src.isMesh) src.geometry.computeVertexNormals();
      views.source.render();
    }
    status(`live frame ${r.frame.seq}: ${r.frame.latency_ms.toFixed(1)} ms`);
    if (s.live) state.liveFrames = r.frame.seq;
  }
};

start().catch((err) => showError(err.message || String(err)));
