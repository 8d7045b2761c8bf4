// The web viewer of haptic-viewer --web: one WebSocket to the relay (client-viewer/src/web.rs),
// haptics.v1.SurfaceFrame protobuf messages in the compact encoding (keyframes and quantized
// deltas, haptics_proto::delta), JSON status once a second; rendered with three.js.
import * as THREE from 'three';
import { OrbitControls } from '/vendor/OrbitControls.js';

// ---------------------------------------------------------------------------------------------
// Protobuf: the fields of SurfaceFrame this page reads (proto/haptics/v1/haptics.proto).
// ---------------------------------------------------------------------------------------------
class Reader {
  constructor(bytes) { this.b = bytes; this.p = 0; this.v = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength); }
  done() { return this.p >= this.b.length; }
  varint() {
    let x = 0, scale = 1;
    for (let i = 0; i < 10; i++) {
      if (this.p >= this.b.length) throw new Error('truncated varint');
      const c = this.b[this.p++];
      x += (c & 0x7f) * scale;
      if (c < 0x80) return x;
      scale *= 128;
    }
    throw new Error('varint too long');
  }
  double() { if (this.p + 8 > this.b.length) throw new Error('truncated double'); const x = this.v.getFloat64(this.p, true); this.p += 8; return x; }
  bytes() { const n = this.varint(); if (this.p + n > this.b.length) throw new Error('truncated field'); const s = this.b.subarray(this.p, this.p + n); this.p += n; return s; }
  skip(wire) {
    if (wire === 0) this.varint();
    else if (wire === 1) this.p += 8;
    else if (wire === 2) this.bytes();
    else if (wire === 5) this.p += 4;
    else throw new Error('unknown wire type ' + wire);
  }
}

function floats(bytes) {
  if (bytes.length % 4) throw new Error('packed floats not a multiple of 4 bytes');
  return new Float32Array(bytes.slice().buffer);
}

function varints(bytes) {
  const r = new Reader(bytes), out = [];
  while (!r.done()) out.push(r.varint());
  return Uint32Array.from(out);
}

function vec3(bytes) {
  const r = new Reader(bytes), v = [0, 0, 0];
  while (!r.done()) {
    const key = r.varint(), field = Math.floor(key / 8), wire = key & 7;
    if (wire === 1 && field >= 1 && field <= 3) v[field - 1] = r.double(); else r.skip(wire);
  }
  return v;
}

// A ToolProbe (SurfaceFrame.tools, issue 50): one tool's probe.
function decodeTool(bytes) {
  const r = new Reader(bytes);
  const t = { toolId: '', slot: 0, probe: null, force: [0, 0, 0], inContact: false, probeRadius: 0 };
  while (!r.done()) {
    const key = r.varint(), field = Math.floor(key / 8), wire = key & 7;
    switch (field) {
      case 1: t.toolId = new TextDecoder().decode(r.bytes()); break;
      case 2: t.slot = r.varint(); break;
      case 3: t.probe = vec3(r.bytes()); break;
      case 4: t.force = vec3(r.bytes()); break;
      case 5: t.inContact = r.varint() !== 0; break;
      case 6: t.probeRadius = r.double(); break;
      default: r.skip(wire);
    }
  }
  return t;
}

function decodeFrame(buffer) {
  const r = new Reader(new Uint8Array(buffer));
  const f = { frame: 0, simTime: 0, keyframe: false, positions: null, triangles: null,
    probe: null, force: [0, 0, 0], inContact: false, probeRadius: 0, serverTimeUs: 0,
    maxDisplacement: 0, rest: null, watchId: 0, topologyVersion: 0, keyframeId: 0,
    quantum: 0, delta: new Uint8Array(0), baseKeyframeId: 0, referenceDelta: new Uint8Array(0),
    tools: [] };
  while (!r.done()) {
    const key = r.varint(), field = Math.floor(key / 8), wire = key & 7;
    switch (field) {
      case 1: f.frame = r.varint(); break;
      case 2: f.simTime = r.double(); break;
      case 3: f.keyframe = r.varint() !== 0; break;
      case 4: f.positions = floats(r.bytes()); break;
      case 5: f.triangles = varints(r.bytes()); break;
      case 6: f.probe = vec3(r.bytes()); break;
      case 7: f.force = vec3(r.bytes()); break;
      case 8: f.inContact = r.varint() !== 0; break;
      case 9: f.probeRadius = r.double(); break;
      case 10: f.serverTimeUs = r.varint(); break;
      case 11: f.maxDisplacement = r.double(); break;
      case 12: f.rest = floats(r.bytes()); break;
      case 13: f.watchId = r.varint(); break;
      case 14: f.topologyVersion = r.varint(); break;
      case 15: f.keyframeId = r.varint(); break;
      case 16: f.quantum = r.double(); break;
      case 17: f.delta = r.bytes(); break;
      case 18: f.baseKeyframeId = r.varint(); break;
      case 19: f.referenceDelta = r.bytes(); break;
      case 22: f.tools.push(decodeTool(r.bytes())); break;
      default: r.skip(wire);
    }
  }
  return f;
}

// ---------------------------------------------------------------------------------------------
// The delta codec, as haptics_proto::delta: BFS order over the triangle edges, parent
// prediction, zigzag, 16-value blocks with a 5-bit width, LSB-first bit stream.
// ---------------------------------------------------------------------------------------------
function buildCodec(n, triangles) {
  const adj = Array.from({ length: n }, () => []);
  for (let t = 0; t + 2 < triangles.length; t += 3) {
    for (let k = 0; k < 3; k++) {
      const a = triangles[t + k], b = triangles[t + (k + 1) % 3];
      adj[a].push(b); adj[b].push(a);
    }
  }
  for (let i = 0; i < n; i++) {
    const s = adj[i].sort((x, y) => x - y);
    adj[i] = s.filter((x, j) => j === 0 || x !== s[j - 1]);
  }
  const parent = new Int32Array(n).fill(-1), seen = new Uint8Array(n), order = new Uint32Array(n);
  let count = 0;
  for (let root = 0; root < n; root++) {
    if (seen[root]) continue;
    seen[root] = 1;
    const queue = [root];
    for (let h = 0; h < queue.length; h++) {
      const v = queue[h];
      order[count++] = v;
      for (const w of adj[v]) if (!seen[w]) { seen[w] = 1; parent[w] = v; queue.push(w); }
    }
  }
  return { n, order, parent };
}

function decodeDelta(codec, reference, payload, quantum, out) {
  if (payload.length === 0) { out.set(reference); return; }
  const n = codec.n, q = new Float64Array(3 * n);
  let byte = 0, acc = 0, bits = 0;
  const read = (w) => {
    while (bits < w) {
      if (byte >= payload.length) throw new Error('delta truncated');
      acc += payload[byte++] * 2 ** bits;
      bits += 8;
    }
    const m = 2 ** w, v = acc % m;
    acc = Math.floor(acc / m); bits -= w;
    return v;
  };
  let left = 0, width = 0;
  for (let c = 0; c < 3; c++) {
    for (let k = 0; k < n; k++) {
      if (left === 0) {
        width = read(5);
        if (width > 28) throw new Error('delta block width above 28');
        left = 16;
      }
      const u = read(width); left--;
      const v = codec.order[k], p = codec.parent[v];
      const r = (u % 2) ? -(u + 1) / 2 : u / 2;
      q[3 * v + c] = (p < 0 ? 0 : q[3 * p + c]) + r;
    }
  }
  if (byte !== payload.length) throw new Error('delta has trailing bytes');
  for (let i = 0; i < 3 * n; i++) out[i] = reference[i] + q[i] * quantum;
}

// ---------------------------------------------------------------------------------------------
// Scene.
// ---------------------------------------------------------------------------------------------
let dirty = true; // something changed since the last draw
const view = document.getElementById('view');
const statusEl = document.getElementById('status');
const messageEl = document.getElementById('message');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
view.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1d2025);
const camera = new THREE.PerspectiveCamera(35, 1, 1e-4, 10);
camera.up.set(0, 0, 1);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
scene.add(sun);
scene.add(sun.target);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = false;

const material = new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide });
let mesh = null;
const probe = new THREE.Mesh(new THREE.SphereGeometry(1, 24, 16),
  new THREE.MeshLambertMaterial({ color: 0x9aa0a6, transparent: true, opacity: 0.55 }));
probe.visible = false;
scene.add(probe);
const arrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.01, 0xffd54a);
arrow.visible = false;
scene.add(arrow);
// Every tool's probe and force arrow (issue 50): slot 0 uses `probe` and `arrow` above, the
// other slots get their own, made on first use; arrow colours by slot.
const TOOL_COLORS = [0xffd54a, 0x66bb6a, 0xef5350, 0x42a5f5];
const toolMarks = new Map(); // slot -> { probe, arrow }
function toolMark(slot) {
  if (slot === 0) return { probe, arrow };
  if (!toolMarks.has(slot)) {
    const p = new THREE.Mesh(new THREE.SphereGeometry(1, 24, 16),
      new THREE.MeshLambertMaterial({ color: 0x9aa0a6, transparent: true, opacity: 0.55 }));
    const a = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.01,
      TOOL_COLORS[slot % TOOL_COLORS.length]);
    p.visible = false; a.visible = false;
    scene.add(p); scene.add(a);
    toolMarks.set(slot, { probe: p, arrow: a });
  }
  return toolMarks.get(slot);
}
const FORCE_SCALE_M_PER_N = 0.1; // as haptic-viewer's PNGs: 100 mm per newton
const MIN_COLOR_SCALE_M = 0.5e-3;

// Colour map of client-viewer/src/raster.rs: blue (0) - light grey (0.5) - red (1), sRGB.
const STOPS = [[0.23, 0.30, 0.75], [0.87, 0.87, 0.87], [0.71, 0.02, 0.15]];
function colormap(t) {
  t = Number.isFinite(t) ? Math.min(Math.max(t, 0), 1) : 0;
  const [a, b, s] = t < 0.5 ? [STOPS[0], STOPS[1], 2 * t] : [STOPS[1], STOPS[2], 2 * t - 1];
  return [a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s, a[2] + (b[2] - a[2]) * s];
}
(function drawColorbar() {
  const c = document.getElementById('colorbar'), g = c.getContext('2d');
  for (let y = 0; y < c.height; y++) {
    const [r, gg, b] = colormap(1 - y / (c.height - 1));
    g.fillStyle = `rgb(${r * 255},${gg * 255},${b * 255})`;
    g.fillRect(0, y, c.width, 1);
  }
})();

let home = null; // { position, target }
function frameCamera(positions) {
  const box = new THREE.Box3().setFromArray(positions);
  const c = box.getCenter(new THREE.Vector3());
  const r = box.getSize(new THREE.Vector3()).length() / 2 || 0.05;
  const dir = new THREE.Vector3(1, 1, 0.4).normalize();
  const dist = 1.15 * r / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2));
  home = { position: c.clone().addScaledVector(dir, dist), target: c.clone() };
  camera.near = dist / 100; camera.far = dist * 10; camera.updateProjectionMatrix();
  resetView();
}
function resetView() {
  if (!home) return;
  dirty = true;
  camera.position.copy(home.position);
  controls.target.copy(home.target);
  controls.update();
}
document.getElementById('reset').onclick = resetView;

function resize() {
  const w = view.clientWidth, h = view.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1); camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();

// ---------------------------------------------------------------------------------------------
// State of the stream.
// ---------------------------------------------------------------------------------------------
const S = { topology: null, reference: null, positions: null, frames: 0, keyframes: 0,
  badFrames: 0, keyframeRequested: false, forceN: 0, ageMs: null, stats: null,
  fps: 0, windowFrames: 0, windowStart: performance.now(), maxDisplacement: 0, scale: 0 };
const tmpColor = new THREE.Color();

function newTopology(f) {
  const n = f.positions.length / 3;
  const rest = f.rest && f.rest.length === f.positions.length ? f.rest : f.positions.slice();
  S.topology = { version: f.topologyVersion, triangles: f.triangles, rest, codec: buildCodec(n, f.triangles) };
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(3 * n), 3));
  g.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * n), 3));
  g.setIndex(new THREE.BufferAttribute(f.triangles, 1));
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); }
  mesh = new THREE.Mesh(g, material);
  scene.add(mesh);
  S.positions = new Float32Array(3 * n);
  if (!home) frameCamera(f.positions);
}

function requestKeyframe(why) {
  if (S.keyframeRequested || !socket || socket.readyState !== 1) return;
  console.warn('asking for a keyframe: ' + why);
  S.keyframeRequested = true;
  socket.send(JSON.stringify({ type: 'keyframe' }));
}

function applyFrame(f) {
  if (f.keyframe && f.triangles && f.triangles.length) {
    newTopology(f);
  } else if (!S.topology || S.topology.version !== f.topologyVersion) {
    return requestKeyframe('topology ' + f.topologyVersion + ' is new');
  }
  const n3 = S.topology.rest.length;
  if (f.keyframe && !f.positions && f.baseKeyframeId) {
    // Chained: the new reference is our reference plus reference_delta.
    if (!S.reference || S.reference.id !== f.baseKeyframeId) return requestKeyframe('base keyframe ' + f.baseKeyframeId + ' missing');
    const next = new Float32Array(n3);
    decodeDelta(S.topology.codec, S.reference.positions, f.referenceDelta, f.quantum, next);
    S.reference = { id: f.keyframeId, positions: next };
    S.keyframes++;
    S.keyframeRequested = false;
  } else if (f.keyframe) {
    if (!f.positions || f.positions.length !== n3) return requestKeyframe('keyframe size');
    S.reference = { id: f.keyframeId, positions: f.positions };
    S.keyframes++;
    S.keyframeRequested = false;
  }
  if (f.quantum > 0 && !(f.positions && !f.keyframe)) {
    if (!S.reference || S.reference.id !== f.keyframeId) return requestKeyframe('keyframe ' + f.keyframeId + ' missing');
    decodeDelta(S.topology.codec, S.reference.positions, f.delta, f.quantum, S.positions);
  } else if (f.positions && f.positions.length === n3) {
    S.positions.set(f.positions);
  } else {
    return requestKeyframe('frame size');
  }
  updateMesh();
  updateProbe(f);
  dirty = true;
  S.frames++; S.windowFrames++;
  if (f.serverTimeUs > 0) S.ageMs = Date.now() - f.serverTimeUs / 1000;
}

function updateMesh() {
  const g = mesh.geometry, pos = g.attributes.position, col = g.attributes.color;
  const p = S.positions, rest = S.topology.rest, n = p.length / 3;
  pos.array.set(p);
  let maxd = 0;
  const d = new Float32Array(n);
  for (let i = 0; i < n; i++) {
    const dx = p[3 * i] - rest[3 * i], dy = p[3 * i + 1] - rest[3 * i + 1], dz = p[3 * i + 2] - rest[3 * i + 2];
    d[i] = Math.sqrt(dx * dx + dy * dy + dz * dz);
    if (d[i] > maxd) maxd = d[i];
  }
  const scale = Math.max(maxd, MIN_COLOR_SCALE_M);
  for (let i = 0; i < n; i++) {
    const [r, gg, b] = colormap(d[i] / scale);
    tmpColor.setRGB(r, gg, b, THREE.SRGBColorSpace);
    col.array[3 * i] = tmpColor.r; col.array[3 * i + 1] = tmpColor.g; col.array[3 * i + 2] = tmpColor.b;
  }
  pos.needsUpdate = true; col.needsUpdate = true;
  g.computeVertexNormals();
  g.computeBoundingSphere();
  S.maxDisplacement = maxd; S.scale = scale;
  document.getElementById('legend-max').textContent = (scale * 1e3).toFixed(2) + ' mm';
  document.getElementById('legend-mid').textContent = (scale * 500).toFixed(2) + ' mm';
}

// Places one tool's sphere and force arrow; returns the force magnitude, N.
function placeTool(mark, t) {
  const ok = t.probe && t.probe.every(Number.isFinite) && t.probeRadius > 0;
  mark.probe.visible = !!ok;
  const F = new THREE.Vector3(...t.force);
  const n = F.length();
  if (!ok) { mark.arrow.visible = false; return n; }
  mark.probe.position.set(...t.probe);
  mark.probe.scale.setScalar(t.probeRadius);
  mark.probe.material.color.set(t.inContact ? 0xf0f0f0 : 0x9aa0a6);
  if (n > 1e-4) {
    const len = n * FORCE_SCALE_M_PER_N;
    mark.arrow.position.copy(mark.probe.position);
    mark.arrow.setDirection(F.clone().normalize());
    mark.arrow.setLength(len, Math.min(0.3 * len, 0.004), Math.min(0.15 * len, 0.002));
    mark.arrow.visible = true;
  } else {
    mark.arrow.visible = false;
  }
  return n;
}

// The probes of a frame: every tool of `tools` (issue 50), or the one probe of fields 6-9 from
// daemons that send no tools. S.forceN is the first tool's force (slot 0's).
function updateProbe(f) {
  const now = performance.now();
  if (!f.tools.length) {
    S.forceN = placeTool(toolMark(0), f);
    for (const m of toolMarks.values()) { m.probe.visible = false; m.arrow.visible = false; }
    chartPush(toolChart(0, '').force, [now, S.forceN]);
    return;
  }
  const seen = new Set();
  for (const t of f.tools) {
    const n = placeTool(toolMark(t.slot), { ...t, probeRadius: t.probeRadius || f.probeRadius });
    seen.add(t.slot);
    chartPush(toolChart(t.slot, t.toolId).force, [now, n]);
  }
  S.forceN = new THREE.Vector3(...f.force).length();
  if (!seen.has(0)) { probe.visible = false; arrow.visible = false; }
  for (const [slot, m] of toolMarks) if (!seen.has(slot)) { m.probe.visible = false; m.arrow.visible = false; }
}

function showStatus() {
  const now = performance.now();
  if (now - S.windowStart >= 1000) {
    S.fps = S.windowFrames * 1000 / (now - S.windowStart);
    S.windowFrames = 0; S.windowStart = now;
  }
  const st = S.stats;
  const fmt = (x, d) => (x === undefined || x === null || !Number.isFinite(x)) ? '-' : x.toFixed(d);
  const parts = [
    'loop ' + fmt(st && st.loop_rate_hz, 1) + ' Hz',
    'step p50 ' + fmt(st && st.step_p50_us, 0) + ' us p99 ' + fmt(st && st.step_p99_us, 0) + ' us',
    'force ' + S.forceN.toFixed(3) + ' N',
    'frame age ' + fmt(S.ageMs, 0) + ' ms',
    fmt(S.fps, 1) + ' fps',
    'max disp ' + (S.maxDisplacement * 1e3).toFixed(2) + ' mm',
  ];
  if (st && st.faulted) parts.push('FAULT: ' + st.fault);
  statusEl.textContent = parts.join(' \u00b7 ');
  statusEl.dataset.forceN = String(S.forceN);
  statusEl.dataset.frames = String(S.frames);
}

// ---------------------------------------------------------------------------------------------
// Strip chart: the force magnitude (from every frame) and the pose-to-force latency p50 / p99
// (from the status message, once a second) over the last CHART_WINDOW_MS.
// ---------------------------------------------------------------------------------------------
const CHART_WINDOW_MS = 10000;
// One strip chart per tool slot (issue 50): slot 0 is the page's #chart, the others copies of
// it made on first use, stacked above it.
const charts = new Map(); // slot -> { force: [t_ms, N], latency: [t_ms, p50_ms, p99_ms], box, canvas, toolId }
function toolChart(slot, toolId) {
  if (!charts.has(slot)) {
    let box = document.getElementById('chart');
    if (slot !== 0) {
      box = box.cloneNode(true);
      box.id = 'chart-' + slot;
      box.querySelectorAll('[id]').forEach((e) => { e.id = e.id + '-' + slot; });
      document.body.appendChild(box);
    }
    box.style.bottom = `calc(2.8em + ${slot * 150}px)`;
    charts.set(slot, { force: [], latency: [], box, canvas: box.querySelector('canvas'), toolId });
  }
  const c = charts.get(slot);
  if (toolId !== undefined && toolId !== c.toolId) c.toolId = toolId;
  return c;
}
const chart = toolChart(0, '');
const strip = chart.canvas;

function chartPush(series, sample) {
  series.push(sample);
  while (series.length && sample[0] - series[0][0] > CHART_WINDOW_MS) series.shift();
}

// A polyline of series[k] against time on `canvas`, scaled so that `top` reaches its top.
function chartLine(canvas, series, k, top, now, color) {
  const g = canvas.getContext('2d'), w = canvas.width, h = canvas.height;
  g.strokeStyle = color;
  g.lineWidth = 1.5;
  g.beginPath();
  series.forEach((p, i) => {
    const x = w - (now - p[0]) / CHART_WINDOW_MS * w;
    const y = h - 2 - Math.min(p[k] / top, 1) * (h - 4);
    if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
  });
  g.stroke();
}

function drawToolChart(slot, c, now) {
  for (const series of [c.force, c.latency]) {
    while (series.length && now - series[0][0] > CHART_WINDOW_MS) series.shift();
  }
  const canvas = c.canvas, g = canvas.getContext('2d'), w = canvas.width, h = canvas.height;
  g.clearRect(0, 0, w, h);
  g.strokeStyle = '#454b55';
  g.lineWidth = 1;
  for (let s = 1; s < 10; s++) { // one line a second
    const x = Math.round(s / 10 * w) + 0.5;
    g.beginPath(); g.moveTo(x, 0); g.lineTo(x, h); g.stroke();
  }
  const forceTop = Math.max(0.01, ...c.force.map((p) => p[1])) * 1.1;
  const latencyTop = Math.max(1, ...c.latency.map((p) => p[2])) * 1.1;
  chartLine(canvas, c.latency, 1, latencyTop, now, '#4fc3f7');
  chartLine(canvas, c.latency, 2, latencyTop, now, '#b39ddb');
  chartLine(canvas, c.force, 1, forceTop, now, '#ff9e3d');
  const last = c.latency[c.latency.length - 1];
  const lastForce = c.force.length ? c.force[c.force.length - 1][1] : 0;
  const suffix = slot === 0 ? '' : '-' + slot;
  const name = c.toolId ? `tool ${c.toolId}: ` : (charts.size > 1 ? `slot ${slot}: ` : '');
  document.getElementById('chart-force' + suffix).textContent =
    `${name}${lastForce.toFixed(3)} N (axis ${forceTop.toFixed(3)} N)`;
  document.getElementById('chart-latency' + suffix).textContent = last
    ? `${last[1].toFixed(2)} / ${last[2].toFixed(2)} ms (axis ${latencyTop.toFixed(1)} ms)` : '-';
}

function drawChart() {
  const now = performance.now();
  for (const [slot, c] of charts) drawToolChart(slot, c, now);
}
setInterval(drawChart, 100);

// Draw only when something changed (a frame, the camera, the size): an idle page costs nothing.
controls.addEventListener('change', () => { dirty = true; });
window.addEventListener('resize', () => { dirty = true; });
function render() {
  requestAnimationFrame(render);
  if (!dirty) return;
  dirty = false;
  renderer.render(scene, camera);
}
render();
setInterval(showStatus, 250);

// ---------------------------------------------------------------------------------------------
// Sessions and the socket.
// ---------------------------------------------------------------------------------------------
let socket = null;
const params = new URLSearchParams(location.search);
const select = document.getElementById('sessions');
const rateSelect = document.getElementById('rate');
if (params.get('rate')) {
  const o = document.createElement('option'); o.textContent = params.get('rate'); o.selected = true;
  rateSelect.appendChild(o);
}

async function listSessions() {
  const r = await fetch('/api/sessions');
  const list = await r.json();
  if (!Array.isArray(list)) throw new Error(list.error || 'no session list');
  const want = select.value || params.get('session');
  select.innerHTML = '';
  for (const s of list) {
    const o = document.createElement('option');
    o.value = s.session_id;
    o.textContent = `${s.session_id} (${s.scene}, ${s.surface_vertices} surface vertices)`;
    select.appendChild(o);
  }
  if (want && list.some((s) => s.session_id === want)) select.value = want;
  if (!list.length) messageEl.textContent = 'no session is running';
  return list;
}

function connect() {
  if (socket) { socket.onclose = null; socket.close(); }
  Object.assign(S, { topology: null, reference: null, keyframeRequested: false, frames: 0 });
  for (const [slot, c] of charts) {
    c.force.length = 0; c.latency.length = 0;
    if (slot !== 0) { c.box.remove(); charts.delete(slot); }
  }
  for (const m of toolMarks.values()) { scene.remove(m.probe); scene.remove(m.arrow); }
  toolMarks.clear();
  const id = select.value;
  if (!id) return;
  messageEl.textContent = 'waiting for the first keyframe...';
  const proto = location.protocol === 'https:' ? 'wss' : 'ws';
  socket = new WebSocket(`${proto}://${location.host}/ws?session=${encodeURIComponent(id)}&rate=${rateSelect.value}`);
  socket.binaryType = 'arraybuffer';
  socket.onmessage = (ev) => {
    if (typeof ev.data === 'string') {
      const m = JSON.parse(ev.data);
      if (m.type === 'status') {
        S.stats = m;
        const now = performance.now();
        if (m.tools && m.tools.length) {
          // Each tool's own figures (issue 50), on its own chart.
          for (const t of m.tools) {
            if (t.connected && t.pose_to_force_p50_us > 0) {
              chartPush(toolChart(t.slot, t.tool_id).latency,
                [now, t.pose_to_force_p50_us / 1e3, t.pose_to_force_p99_us / 1e3]);
            }
          }
        } else if (m.pose_to_force_p50_us > 0) {
          chartPush(chart.latency, [now, m.pose_to_force_p50_us / 1e3, m.pose_to_force_p99_us / 1e3]);
        }
        document.getElementById('scene').textContent = `${m.scene}: ${m.nodes} nodes, ${m.tetrahedra} elements`;
      } else if (m.type === 'error') messageEl.textContent = 'error: ' + m.message;
      else if (m.type === 'ended') messageEl.textContent = 'the session ended';
      return;
    }
    try {
      applyFrame(decodeFrame(ev.data));
      if (S.frames === 1) messageEl.textContent = '';
    } catch (e) {
      S.badFrames++;
      console.error(e);
      requestKeyframe(String(e));
    }
  };
  socket.onclose = () => { if (!messageEl.textContent) messageEl.textContent = 'disconnected'; };
}

select.onchange = () => { home = null; connect(); };
rateSelect.onchange = () => {
  if (socket && socket.readyState === 1) socket.send(JSON.stringify({ type: 'rate', hz: Number(rateSelect.value) }));
};
document.getElementById('refresh').onclick = () => listSessions().catch((e) => { messageEl.textContent = String(e); });

listSessions().then(connect).catch((e) => { messageEl.textContent = String(e); });

// For tests and the curious: the state, the camera (copies: reading it changes nothing), and the
// probe's position on the screen (CSS pixels).
window.hapticViewer = {
  state: S,
  camera() {
    return { position: camera.position.toArray(), target: controls.target.toArray(),
      home: home && { position: home.position.toArray(), target: home.target.toArray() } };
  },
  // The strip chart's samples (copies) and where it sits on the screen (CSS pixels).
  chart(slot = 0) {
    const t = charts.get(slot);
    if (!t) return null;
    const c = t.canvas.getBoundingClientRect(), box = t.box.getBoundingClientRect();
    return { force: t.force.map((p) => p.slice()), latency: t.latency.map((p) => p.slice()),
      windowMs: CHART_WINDOW_MS, now: performance.now(), forceN: S.forceN, toolId: t.toolId,
      canvas: [c.left, c.top, c.width, c.height], box: [box.left, box.top, box.width, box.height] };
  },
  // The tools of the last frame: slot, id, whether its probe and arrow show (issue 50).
  tools() {
    const out = [{ slot: 0, probe: probe.visible, arrow: arrow.visible }];
    for (const [slot, m] of toolMarks) out.push({ slot, probe: m.probe.visible, arrow: m.arrow.visible });
    return out.map((t) => ({ ...t, toolId: charts.has(t.slot) ? charts.get(t.slot).toolId : '' }));
  },
  probeScreen() {
    if (!probe.visible) return null;
    const v = probe.position.clone().project(camera), rect = renderer.domElement.getBoundingClientRect();
    return [rect.left + (v.x + 1) / 2 * rect.width, rect.top + (1 - v.y) / 2 * rect.height];
  },
};
