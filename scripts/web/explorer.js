// orthodiff explorer: the skin at x0 + S dp (paper eq. 7) redrawn at every slider event,
// true and corrected solves, re-linearisation, planning and matching through the JSON API
// of scripts/explore_web.py. three.js comes from npm (scripts/web/node_modules), served
// locally. Units: mm and degrees, in the scene's frame (x left, y anterior, z superior).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);
// Colour map stops (the legend's CSS gradient, sRGB) as three.js's linear RGB.
const STOPS = [0x30123b, 0x4686fb, 0x1be5b5, 0xa4fc3c, 0xfb8022, 0x7a0403].map((hex) => {
  const c = new THREE.Color(hex);   // converted from sRGB to the working (linear) space
  return [c.r, c.g, c.b];
});
const SKIN = new THREE.Color(0xe2b59c);   // a skin tone (sRGB), the default colour
const BONE = 0xebe4d2;                    // ivory

const state = {
  names: [], units: [], bounds: [], p0: null, p: null,
  x0: null, rest: null, S: null, nP: 0, nV: 0,
  lm0: null, lmS: null, lmNames: [], targets: null,
  bone: null,         // the bone under the skin (GET /api/scene's bone), drawn on demand
  validation: null,   // |predicted - real skin| mm per vertex (NaN: not in the scan), or null
  colourMax: null,    // the colour map's top, mm
  shown: null,        // Float32Array (nV*3) drawn now: the prediction, or a solve's answer
  error: null,        // per-vertex |answer - prediction| after Solve/Corrected, else null
  pending: null,      // timeStamp of the slider event waiting for its frame
  busy: false,
};

const explorer = {
  ready: false,
  lastFrameMs: NaN,
  frames: 0,
  setParams,
  skinPositions: () => Float32Array.from(state.shown),
  params: () => Object.fromEntries(state.names.map((n, i) => [n, state.p[i]])),
  errorMapMax: () => (state.error ? state.error.reduce((a, b) => Math.max(a, b), 0) : null),
  showBone: (on) => { $('bone').checked = on; return showBone(); },
  bonePositions: () => (boneMesh.visible
    ? Float32Array.from(boneGeometry.getAttribute('position').array) : null),
  skinOpacity: () => mesh.material.opacity,
  validationMax: () => ($('colour').value === 'validation' && !state.error
    ? state.colourMax : null),
  lastError: null,
};
window.explorer = explorer;

// ---------------------------------------------------------------- three.js scene
const view = $('view');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
view.appendChild(renderer.domElement);
const scene3 = new THREE.Scene();
scene3.background = new THREE.Color(0x1d2026);
const camera = new THREE.PerspectiveCamera(30, 1, 1, 5000);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
controls.addEventListener('change', () => requestFrame());
scene3.add(new THREE.HemisphereLight(0xffffff, 0x404040, 0.7));
const sun = new THREE.DirectionalLight(0xffffff, 1.1);
scene3.add(sun);
const geometry = new THREE.BufferGeometry();
const mesh = new THREE.Mesh(geometry, new THREE.MeshLambertMaterial(
  { vertexColors: true, side: THREE.DoubleSide }));
mesh.frustumCulled = false;   // the skin moves: its bounding sphere is the rest one's
scene3.add(mesh);
const boneGeometry = new THREE.BufferGeometry();
const boneMesh = new THREE.Mesh(boneGeometry, new THREE.MeshLambertMaterial({ color: BONE }));
boneMesh.frustumCulled = false;
boneMesh.visible = false;
scene3.add(boneMesh);
const markers = new THREE.Group();
scene3.add(markers);
let center = new THREE.Vector3(), radius = 100;

function resize() {
  const w = view.clientWidth, h = view.clientHeight;
  renderer.setSize(w, h);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  requestFrame();
}
window.addEventListener('resize', resize);

// the head frame's axes in the scene's frame (left, anterior, superior): the views are the face's
let headAxes = [new THREE.Vector3(1, 0, 0), new THREE.Vector3(0, 1, 0), new THREE.Vector3(0, 0, 1)];

function look(view) {   // front: from anterior (+y); profile: from the patient's right (-x)
  const dir = view === 'front' ? headAxes[1].clone() : headAxes[0].clone().negate();
  camera.up.copy(headAxes[2]);   // the orbit axis too (OrbitControls keeps it from its start)
  controls._quat.setFromUnitVectors(camera.up, new THREE.Vector3(0, 1, 0));
  controls._quatInverse.copy(controls._quat).invert();
  camera.position.copy(center).addScaledVector(dir, 3.2 * radius);
  controls.target.copy(center);
  controls.update();
  requestFrame();
}

// ---------------------------------------------------------------- API
async function api(path, body) {
  const opts = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) };
  const r = await fetch(path, opts);
  const isJson = (r.headers.get('content-type') || '').includes('json');
  const data = isJson ? await r.json() : await r.arrayBuffer();
  if (!r.ok) throw new Error(`${path}: ${r.status} ${isJson ? data.error : ''}`);
  return data;
}

async function loadScene() {
  const [s, buf] = await Promise.all([api('/api/scene'), api('/api/sensitivity')]);
  state.names = s.param_names; state.units = s.units; state.bounds = s.bounds;
  state.p0 = Float64Array.from(s.p0); state.p = Float64Array.from(s.p0);
  state.nP = s.param_names.length; state.nV = s.vertices.length;
  state.x0 = Float64Array.from(s.vertices.flat());
  state.rest = Float64Array.from(s.vertices_rest.flat());
  state.S = new Float32Array(buf);    // (nV, 3, nP), little-endian, C order
  state.lmNames = Object.keys(s.landmarks);
  state.lm0 = Float64Array.from(state.lmNames.flatMap((n) => s.landmarks[n]));
  state.lmS = Float64Array.from(s.landmark_sensitivity.flat(2));   // (L, 3, nP)
  state.targets = s.targets;
  headAxes = s.head_axes.map((a) => new THREE.Vector3(...a));
  state.bone = {
    rest: Float64Array.from(s.bone.vertices.flat()), segment: Int32Array.from(s.bone.segment),
    T: s.bone.transforms, dT: s.bone.transform_derivatives };
  boneGeometry.setAttribute('position', new THREE.BufferAttribute(
    new Float32Array(state.bone.rest.length), 3));
  boneGeometry.setIndex(s.bone.triangles.flat());
  $('occlusion').value = s.occlusion;
  state.band = s.band && Float32Array.from(s.band.r95_mm);
  state.lmBand = s.band && s.band.landmarks;
  $('colour').querySelector('option[value="band"]').disabled = !state.band;
  state.validation = s.validation && Float32Array.from(
    s.validation.signed_distance_mm, (v) => (v === null ? NaN : Math.abs(v)));
  if (state.validation && !$('colour').querySelector('option[value="validation"]')) {
    $('colour').add(new Option('validation: predicted to real skin', 'validation'));
    $('colour').value = 'validation';
  }
  const first = geometry.getAttribute('position') === undefined
    || geometry.getAttribute('position').count !== state.nV;
  if (first) {
    geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(3 * state.nV), 3));
    geometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * state.nV), 3));
    geometry.setIndex(s.triangles.flat());
  }
  state.shown = new Float32Array(3 * state.nV);
  state.error = null;
  buildSliders();
  buildMarkers();
  predict();
  if (first) {
    geometry.getAttribute('position').array.set(state.shown);
    geometry.computeBoundingSphere();
    center = geometry.boundingSphere.center.clone();
    radius = geometry.boundingSphere.radius;
    camera.near = radius / 20; camera.far = radius * 20;
    look('front');
  }
}

// ---------------------------------------------------------------- first-order prediction
function dp() {
  const d = new Float64Array(state.nP);
  for (let j = 0; j < state.nP; j++) d[j] = state.p[j] - state.p0[j];
  return d;
}

function predict() {   // state.shown = x0 + S dp, a typed-array loop over the moved parameters
  const d = dp(), nP = state.nP, S = state.S, x0 = state.x0, out = state.shown;
  const moved = [];
  for (let j = 0; j < nP; j++) if (d[j] !== 0) moved.push(j);
  for (let i = 0, n = x0.length; i < n; i++) {
    let v = x0[i];
    const row = i * nP;
    for (const j of moved) v += S[row + j] * d[j];
    out[i] = v;
  }
  state.error = null;
  if (state.bone) state.bone.exact = null;
}

function predictedLandmarks() {
  const d = dp(), nP = state.nP, out = new Float64Array(state.lm0.length);
  for (let i = 0; i < out.length; i++) {
    let v = state.lm0[i];
    for (let j = 0; j < nP; j++) v += state.lmS[i * nP + j] * d[j];
    out[i] = v;
  }
  return out;
}

// ---------------------------------------------------------------- drawing
function colourise() {
  const n = state.nV, col = geometry.getAttribute('color').array, x = state.shown;
  let value, title;
  if (state.error) {
    value = (i) => state.error[i];
    title = 'first-order error |true - x0 - S dp| mm';
  } else if ($('colour').value === 'skin') {
    for (let i = 0; i < n; i++) { col[3 * i] = SKIN.r; col[3 * i + 1] = SKIN.g; col[3 * i + 2] = SKIN.b; }
    geometry.getAttribute('color').needsUpdate = true;
    $('legend').hidden = true;
    return;
  } else if ($('colour').value === 'validation') {
    value = (i) => state.validation[i];
    title = '|predicted - real skin| mm (validate.py; grey: not in the scan)';
  } else if ($('colour').value === 'band') {
    value = (i) => state.band[i];
    title = "the tissue's 95 % band at p0, mm (its prior: docs/uncertainty.md)";
  } else {
    const ref = $('colour').value === 'rest' ? state.rest : state.x0;
    value = (i) => Math.hypot(x[3 * i] - ref[3 * i], x[3 * i + 1] - ref[3 * i + 1],
                              x[3 * i + 2] - ref[3 * i + 2]);
    title = `displacement from ${$('colour').value === 'rest' ? 'rest' : 'p0'} mm`;
  }
  const vals = new Float32Array(n);
  let hi = 0;
  for (let i = 0; i < n; i++) { vals[i] = value(i); if (vals[i] > hi) hi = vals[i]; }
  const scale = hi > 1e-9 ? 1 / hi : 0;
  for (let i = 0; i < n; i++) {
    if (Number.isNaN(vals[i])) { col[3 * i] = col[3 * i + 1] = col[3 * i + 2] = 0.5; continue; }
    const t = Math.min(vals[i] * scale, 1) * (STOPS.length - 1);
    const k = Math.min(Math.floor(t), STOPS.length - 2), f = t - k;
    const a = STOPS[k], b = STOPS[k + 1];
    col[3 * i] = a[0] + f * (b[0] - a[0]);
    col[3 * i + 1] = a[1] + f * (b[1] - a[1]);
    col[3 * i + 2] = a[2] + f * (b[2] - a[2]);
  }
  geometry.getAttribute('color').needsUpdate = true;
  $('legend').hidden = false;
  $('legend-title').textContent = title;
  $('legend-hi').textContent = hi.toFixed(2);
  state.colourMax = hi;
}

function buildMarkers() {
  markers.clear();
  const r = Math.max(radius / 90, 0.6);
  const sphere = new THREE.SphereGeometry(r, 12, 8);
  // drawn over the skin: landmarks lie on it, targets often in front of or behind it
  const lmMat = new THREE.MeshBasicMaterial({ color: 0xffffff, depthTest: false });
  const tgMat = new THREE.MeshBasicMaterial({ color: 0xff3b30, depthTest: false });
  state.lmMarkers = state.lmNames.map(() => {
    const m = new THREE.Mesh(sphere, lmMat);
    m.renderOrder = 1;
    markers.add(m);
    return m;
  });
  for (const [, t] of Object.entries(state.targets || {})) {
    const x = targetPoint(t);
    const m = new THREE.Mesh(new THREE.BoxGeometry(1.6 * r, 1.6 * r, 1.6 * r), tgMat);
    m.position.set(x[0], x[1], x[2]);
    m.renderOrder = 1;
    markers.add(m);
  }
}

const HEAD_AXES = ['left', 'anterior', 'superior'];

// A target entry (inverse/objective.py target_entry): [x, y, z] mm, or {at, along}.
function targetPoint(t) {
  return Array.isArray(t) ? t : t.at;
}

// The distance (mm) of point p from target t along the head axes the target holds.
function targetDistance(t, p) {
  const x = targetPoint(t);
  const offset = new THREE.Vector3(p[0] - x[0], p[1] - x[1], p[2] - x[2]);
  const along = Array.isArray(t) ? HEAD_AXES : t.along;
  return Math.sqrt(HEAD_AXES.reduce((sum, a, k) =>
    sum + (along.includes(a) ? offset.dot(headAxes[k]) ** 2 : 0), 0));
}

function updateLandmarks(points) {
  const rows = [];
  state.lmNames.forEach((n, i) => {
    state.lmMarkers[i].position.set(points[3 * i], points[3 * i + 1], points[3 * i + 2]);
    const t = state.targets && state.targets[n];
    if (t) {
      const d = targetDistance(t, points.slice(3 * i, 3 * i + 3));
      const band = state.lmBand ? state.lmBand[n].toFixed(2) : '–';
      rows.push(`<tr><td>${n}</td><td class="num">${d.toFixed(2)}</td>`
        + `<td class="num">${band}</td></tr>`);
    }
  });
  $('landmarks').tBodies[0].innerHTML = rows.join('') ||
    '<tr><td colspan="3">no targets</td></tr>';
}

function showBone() {   // the bone under a see-through skin, or the skin alone
  const on = $('bone').checked;
  boneMesh.visible = on;
  Object.assign(mesh.material, { transparent: on, opacity: on ? 0.35 : 1, depthWrite: !on });
  mesh.material.needsUpdate = true;
  return requestFrame();
}

function placeBone() {   // each segment's vertices by its motion: an answer's exact one, else
  // the first order T0 + dT dp, as the skin
  const b = state.bone, d = dp(), x = boneGeometry.getAttribute('position').array;
  const A = b.exact || b.T.map((T0, k) => T0.map((row, r) => row.map((v, c) => {
    let a = v;
    for (let j = 0; j < state.nP; j++) if (d[j] !== 0) a += b.dT[k][j][r][c] * d[j];
    return a;
  })));
  for (let i = 0; i < b.segment.length; i++) {
    const k = b.segment[i], X = b.rest[3 * i], Y = b.rest[3 * i + 1], Z = b.rest[3 * i + 2];
    if (k < 0) { x[3 * i] = X; x[3 * i + 1] = Y; x[3 * i + 2] = Z; continue; }
    const M = A[k];
    for (let r = 0; r < 3; r++) x[3 * i + r] = M[r][0] * X + M[r][1] * Y + M[r][2] * Z + M[r][3];
  }
  boneGeometry.getAttribute('position').needsUpdate = true;
  vertexNormals(boneGeometry);
}

function vertexNormals(geom = geometry) {   // area-weighted, typed arrays (3x faster than three's)
  const x = geom.getAttribute('position').array, idx = geom.getIndex().array;
  if (!geom.getAttribute('normal')) {
    geom.setAttribute('normal', new THREE.BufferAttribute(new Float32Array(x.length), 3));
  }
  const n = geom.getAttribute('normal').array;
  n.fill(0);
  for (let t = 0; t < idx.length; t += 3) {
    const a = 3 * idx[t], b = 3 * idx[t + 1], c = 3 * idx[t + 2];
    const ux = x[b] - x[a], uy = x[b + 1] - x[a + 1], uz = x[b + 2] - x[a + 2];
    const vx = x[c] - x[a], vy = x[c + 1] - x[a + 1], vz = x[c + 2] - x[a + 2];
    const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    n[a] += nx; n[a + 1] += ny; n[a + 2] += nz;
    n[b] += nx; n[b + 1] += ny; n[b + 2] += nz;
    n[c] += nx; n[c + 1] += ny; n[c + 2] += nz;
  }
  for (let i = 0; i < n.length; i += 3) {
    const l = Math.hypot(n[i], n[i + 1], n[i + 2]) || 1;
    n[i] /= l; n[i + 1] /= l; n[i + 2] /= l;
  }
  geom.getAttribute('normal').needsUpdate = true;
}

let frameQueued = false, frameResolvers = [];
function requestFrame() {
  if (!frameQueued) { frameQueued = true; requestAnimationFrame(draw); }
  return new Promise((resolve) => frameResolvers.push(resolve));
}

function draw() {
  frameQueued = false;
  if (state.shown) {
    if (state.pending !== null && !state.error) predict();
    geometry.getAttribute('position').array.set(state.shown);
    geometry.getAttribute('position').needsUpdate = true;
    vertexNormals();
    colourise();
    if (boneMesh.visible) placeBone();
    if (!state.answerLandmarks) updateLandmarks(predictedLandmarks());
  }
  sun.position.copy(camera.position);
  renderer.render(scene3, camera);
  if (state.pending !== null) {
    renderer.getContext().finish();   // the frame is drawn, not only queued
    explorer.lastFrameMs = performance.now() - state.pending;
    state.pending = null;
  }
  explorer.frames++;
  const done = frameResolvers; frameResolvers = [];
  done.forEach((f) => f());
}

// ---------------------------------------------------------------- sliders
function buildSliders() {
  const box = $('sliders');
  box.innerHTML = '';
  state.names.forEach((name, j) => {
    const [lo, hi] = state.bounds[j];
    const row = document.createElement('div');
    row.className = 'slider';
    row.innerHTML = `<label title="${name}">${name} (${state.units[j]})</label>` +
      `<input type="range" min="${lo}" max="${hi}" step="0.05" value="${state.p[j]}" data-j="${j}">` +
      `<input type="number" min="${lo}" max="${hi}" step="0.1" value="${state.p[j].toFixed(2)}" data-j="${j}">`;
    box.appendChild(row);
  });
  for (const el of box.querySelectorAll('input')) el.addEventListener('input', onSlider);
}

function onSlider(ev) {
  const j = Number(ev.target.dataset.j);
  const v = Number(ev.target.value);
  if (!Number.isFinite(v)) return;
  const [lo, hi] = state.bounds[j];
  state.p[j] = Math.min(Math.max(v, lo), hi);
  syncSlider(j, ev.target);
  moved(ev.timeStamp);
}

function syncSlider(j, except) {
  for (const el of $('sliders').querySelectorAll(`input[data-j="${j}"]`)) {
    if (el !== except) el.value = el.type === 'number' ? state.p[j].toFixed(2) : state.p[j];
  }
}

function moved(timeStamp) {   // drawn at once: Chromium aligns input events to frames, and
  state.pending = timeStamp;   // waiting for the next animation frame adds up to 16 ms
  state.error = null;
  state.answerLandmarks = false;
  draw();
  return Promise.resolve();
}

function setParams(values) {   // test hook: like slider events; resolves once drawn
  for (const [name, v] of Object.entries(values)) {
    const j = state.names.indexOf(name);
    if (j < 0) throw new Error(`unknown parameter ${name}`);
    state.p[j] = Number(v);
    syncSlider(j, null);
  }
  return moved(performance.now());
}

// ---------------------------------------------------------------- buttons
function status(text, error = false) {
  $('status').textContent = text;
  $('status').classList.toggle('error', error);
}

async function action(label, fn) {
  if (state.busy) return;
  state.busy = true;
  for (const b of document.querySelectorAll('#panel button')) b.disabled = true;
  status(`${label}…`);
  try {
    await fn();
    explorer.lastError = null;
  } catch (e) {
    explorer.lastError = String(e.message || e);
    status(`${label} failed: ${explorer.lastError}`, true);
  } finally {
    state.busy = false;
    for (const b of document.querySelectorAll('#panel button')) b.disabled = false;
  }
}

function showAnswer(r, label) {   // the answer's skin, coloured by the first-order error
  predict();   // the first-order skin at these parameters
  const first = state.shown;
  const x = Float32Array.from(r.vertices.flat());
  state.shown = x;
  state.error = new Float32Array(state.nV);
  for (let i = 0; i < state.nV; i++) {
    state.error[i] = Math.hypot(x[3 * i] - first[3 * i], x[3 * i + 1] - first[3 * i + 1],
                                x[3 * i + 2] - first[3 * i + 2]);
  }
  state.answerLandmarks = true;
  if (state.bone) state.bone.exact = r.transforms;   // the segments' motions at p, exact
  updateLandmarks(state.lmNames.flatMap((n) => r.landmarks[n]));
  status(`${label}: ${r.iterations} iterations, ${r.seconds.toFixed(2)} s; ` +
         `first-order error max ${r.first_order_error_max_mm.toFixed(3)} mm`);
  return requestFrame();
}

async function reload(p, message) {   // after p0 moved: new scene data, sliders at p
  await loadScene();
  if (p) {
    state.names.forEach((n, j) => { if (n in p) state.p[j] = p[n]; syncSlider(j, null); });
    predict();
  }
  await requestFrame();
  status(message);
}

async function plan() {
  const bar = $('progress');
  bar.hidden = false; bar.value = 0;
  let polling = true;
  const poll = (async () => {
    while (polling) {
      try {
        const pr = await api('/api/progress');
        const h = pr.history;
        if (h.length) {
          const d0 = h[0].mean_distance_mm, d = h[h.length - 1].mean_distance_mm;
          bar.value = d0 > 0 ? Math.min(1, (d0 - d) / d0) : 1;
          status(`planning: iteration ${h[h.length - 1].iteration}, mean distance ` +
                 `${d.toFixed(2)} mm (from ${d0.toFixed(2)})`);
        }
      } catch (e) { /* the plan's own request reports failures */ }
      await new Promise((r) => setTimeout(r, 300));
    }
  })();
  try {
    const r = await api('/api/plan', { targets: state.targets, occlusion: $('occlusion').value });
    bar.value = 1;
    await reload(Object.fromEntries(r.param_names.map((n, i) => [n, r.params_optimal[i]])),
      `plan: ${r.gn_iterations} Gauss-Newton iterations, mean distance ` +
      `${r.mean_distance_before_mm.toFixed(2)} -> ${r.mean_distance_after_mm.toFixed(2)} mm ` +
      `in ${r.seconds.toFixed(1)} s (${r.stop_reason})`);
  } finally {
    polling = false;
    await poll;
    bar.hidden = true;
  }
}

function download(name, data) {
  const a = document.createElement('a');
  a.href = URL.createObjectURL(new Blob([JSON.stringify(data, null, 2)], { type: 'application/json' }));
  a.download = name;
  a.click();
  URL.revokeObjectURL(a.href);
}

function wire() {
  $('front').onclick = () => look('front');
  $('profile').onclick = () => look('profile');
  $('colour').onchange = () => requestFrame();
  $('bone').onchange = showBone;
  $('solve').onclick = () => action('Solve', async () =>
    showAnswer(await api('/api/solve', { p: explorer.params() }), 'true equilibrium'));
  $('corrected').onclick = () => action('Corrected', async () =>
    showAnswer(await api('/api/corrected', { p: explorer.params() }), 'corrected prediction'));
  $('relinearise').onclick = () => action('Re-linearise', async () => {
    const r = await api('/api/relinearise', { p: explorer.params() });
    await reload(null, `re-linearised here in ${r.seconds.toFixed(2)} s`);
  });
  $('plan').onclick = () => action('Plan', plan);
  $('match').onclick = () => action('Match', async () => {
    const r = await api('/api/match', { p: explorer.params() });
    await reload(r.p, `match: true face within ${r.distance_max_mm.toFixed(3)} mm (mean ` +
      `${r.distance_mean_mm.toFixed(3)}) of the predicted one, ${r.gn_iterations} ` +
      `iterations, ${r.seconds.toFixed(1)} s`);
  });
  $('export').onclick = () => action('Export', async () => {
    const r = await api('/api/export', { p: explorer.params() });
    const lm = predictedLandmarks();
    r.landmarks_predicted = Object.fromEntries(state.lmNames.map((n, i) =>
      [n, Array.from(lm.slice(3 * i, 3 * i + 3))]));
    download('orthodiff-plan.json', r);
    status('exported orthodiff-plan.json (parameters, 4x4 transforms per segment, occlusion)');
  });
}

async function start() {
  wire();
  resize();
  try {
    await loadScene();
    await requestFrame();
    status('ready: move a slider (first-order prediction x0 + S dp)');
    explorer.ready = true;
  } catch (e) {
    explorer.lastError = String(e.message || e);
    status(`cannot load the scene: ${explorer.lastError}`, true);
  }
}

start();
