// The kdrt web viewer: lists, uploads and renders meshes through the public API (api.js).
// Plain ES module, no build step; served by kdrt-server from its binary (server/web/).

import * as api from './api.js';
import { OrbitView } from './view.js';

const $ = (id) => document.getElementById(id);
const canvas = $('view');
const ctx2d = canvas.getContext('2d');

/// Frames are drawn over this grey (the page's canvas colour, sRGB level 0.25 = 64): light
/// enough that dark silhouettes and ao creases read, dark enough that a white mesh stands out.
const BACKGROUND_LEVEL = 0.25;
/// Modes whose PNG goes through the sRGB curve (the server's eight_bit_options); the others
/// store their values directly.
const LIGHT_MODES = new Set(['eyelight', 'diffuse']);
/// diffuse: the sun's radiance. With the grey albedo 0.8, a face turned to the sun under the
/// default sky (0.25) reflects 0.8 x (0.6 + 0.25) = 0.68 (sRGB level 0.85), so lit faces keep
/// their shading instead of clipping to white, and a face in shadow 0.2 (0.48).
const SUN = 0.6;
/// Longest side of an interactive frame; larger frames are a job.
const MAX_INTERACTIVE = 2048;
/// Preview frames (while the camera moves) are this much smaller per side, with 1 spp.
const PREVIEW_DIVISOR = 4;
/// Milliseconds without a view change before the full-resolution frame is asked for.
const REST_MS = 200;

const state = {
  meshes: [],
  mesh: null,          // the mesh summary being viewed, or a scene: {id, scene: true, bounds, instances, revision}
  scenes: [],
  view: new OrbitView(),
  inflight: null,      // AbortController of the render in flight
  generation: 0,       // bumps on every view or setting change
  restTimer: 0,
  lastRequest: null,   // the request of the frame on screen
  lastBlob: null,      // its PNG
  lastFull: false,     // whether that frame is the full-resolution one
  job: null,           // the async job being followed
  metricsPrev: null,
};

function srgbToLinear(c) {
  return c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4);
}

function numberInput(id, min, max, fallback) {
  const v = Number($(id).value);
  return Number.isFinite(v) ? Math.min(Math.max(v, min), max) : fallback;
}

function frameSize(divisor) {
  let w = canvas.width, h = canvas.height;
  const s = Math.min(1, MAX_INTERACTIVE / Math.max(w, h));
  w = Math.max(1, Math.round((w * s) / divisor));
  h = Math.max(1, Math.round((h * s) / divisor));
  return [w, h];
}

/// The render request of the current view and settings (full resolution, or a preview).
function renderRequest({ preview = false, format = 'png', size = null, spp = null } = {}) {
  const shading = $('shading').value;
  const [width, height] = size || frameSize(preview ? PREVIEW_DIVISOR : 1);
  const bg = LIGHT_MODES.has(shading) ? srgbToLinear(BACKGROUND_LEVEL) : BACKGROUND_LEVEL;
  const req = {
    [state.mesh.scene ? 'scene' : 'mesh']: state.mesh.id,
    camera: state.view.camera(),
    width,
    height,
    spp: preview ? 1 : (spp || numberInput('spp', 1, 1024, 1)),
    shading,
    background: [bg, bg, bg].map((v) => Number(v.toPrecision(6))),
    format,
  };
  if (shading === 'ao') {
    const samples = numberInput('ao-samples', 1, 4096, 16);
    req.ao_samples = preview ? Math.min(samples, 8) : samples;
    req.ao_distance = numberInput('ao-distance', 0.001, 100, 0.25);
  }
  if (shading === 'diffuse') {
    // A sun that follows the view (from the upper left by default, so the shading shows the
    // shape and the shadows fall down and to the right), and a sky seen through one bounce, so
    // that shadowed parts are dim rather than black.
    req.light = {
      direction: state.view.lightDirection(Number($('light-azimuth').value), Number($('light-elevation').value)),
      intensity: SUN,
    };
    const sky = numberInput('sky', 0, 10, 0.25);
    if (sky > 0) {
      req.bounces = 1;
      req.sky = sky;
    }
  }
  return req;
}

// ---- Errors and the token ----------------------------------------------------------------

function showError(where, error) {
  const el = $(where);
  if (!error) { el.hidden = true; el.textContent = ''; return; }
  if (error.name === 'AbortError') return;
  if (error.status === 401) askForToken(error.message);
  el.textContent = error.message;
  el.hidden = false;
}

function askForToken(detail) {
  $('token-state').textContent = `This server needs a bearer token (${detail}).`;
  $('token').focus();
}

$('token').value = api.token();
$('token-form').addEventListener('submit', (e) => {
  e.preventDefault();
  api.setToken($('token').value.trim());
  $('token-state').textContent = api.token() ? 'Token kept for this tab only.' : 'No token.';
  refreshMeshes().then(refreshScenes);
});

// ---- Meshes --------------------------------------------------------------------------------

function cell(row, text) {
  const td = document.createElement('td');
  td.textContent = text;
  row.append(td);
  return td;
}

function renderMeshTable() {
  const body = $('meshes').querySelector('tbody');
  body.replaceChildren();
  for (const m of state.meshes) {
    const row = document.createElement('tr');
    row.dataset.id = m.id;
    if (state.mesh && state.mesh.id === m.id) row.className = 'selected';
    const name = cell(row, '');
    const view = document.createElement('button');
    view.type = 'button';
    view.textContent = m.id.slice(0, 12);
    view.title = m.id;
    view.setAttribute('aria-label', `View mesh ${m.id.slice(0, 12)}`);
    view.addEventListener('click', () => selectMesh(m));
    name.append(view);
    cell(row, m.triangles.toLocaleString('en'));
    cell(row, `${m.build_ms.toFixed(0)} ms`);
    cell(row, m.in_memory ? 'in memory' : 'on disk');
    const del = document.createElement('button');
    del.type = 'button';
    del.textContent = 'Delete';
    del.setAttribute('aria-label', `Delete mesh ${m.id.slice(0, 12)}`);
    del.addEventListener('click', () => removeMesh(m));
    cell(row, '').append(del);
    body.append(row);
  }
  $('meshes-empty').hidden = state.meshes.length > 0;
}

function showBounds() {
  const m = state.mesh;
  const f = (v) => v.map((x) => x.toPrecision(4)).join(', ');
  if (m && m.scene) {
    $('mesh-bounds').textContent = `scene ${m.id.slice(0, 12)}…: revision ${m.revision}, ${m.instances} instances, bounds [${f(m.bounds.min)}] – [${f(m.bounds.max)}]`;
    return;
  }
  $('mesh-bounds').textContent = m
    ? `${m.id.slice(0, 12)}…: ${m.triangles.toLocaleString('en')} triangles, bounds [${f(m.bounds.min)}] – [${f(m.bounds.max)}]`
    : '';
}

async function refreshMeshes() {
  try {
    state.meshes = await api.listMeshes();
    showError('upload-error', null);
    if (state.mesh && !state.mesh.scene && !state.meshes.some((m) => m.id === state.mesh.id)) state.mesh = null;
    if (!state.mesh && state.meshes.length > 0) selectMesh(state.meshes[0]);
    renderMeshTable();
    showBounds();
  } catch (e) {
    showError('upload-error', e);
  }
}

function selectMesh(m) {
  state.mesh = m;
  state.view.frame(m.bounds);
  renderMeshTable();
  showBounds();
  viewChanged();
}

// ---- Scenes: stored meshes placed by transforms, rendered through /v1/scenes/{id}/render -------

function renderSceneTable() {
  const body = $('scenes').querySelector('tbody');
  body.replaceChildren();
  for (const s of state.scenes) {
    const row = document.createElement('tr');
    row.dataset.id = s.id;
    if (state.mesh && state.mesh.scene && state.mesh.id === s.id) row.className = 'selected';
    const view = document.createElement('button');
    view.type = 'button';
    view.textContent = s.id.slice(0, 12);
    view.title = s.id;
    view.setAttribute('aria-label', `View scene ${s.id.slice(0, 12)}`);
    view.addEventListener('click', () => openScene(s.id));
    cell(row, '').append(view);
    cell(row, String(s.instances));
    cell(row, String(s.revision));
    body.append(row);
  }
  $('scenes-empty').hidden = state.scenes.length > 0;
}

async function refreshScenes() {
  try {
    state.scenes = await api.listScenes();
    renderSceneTable();
  } catch (e) {
    showError('scene-error', e);
  }
}

/// The world box of a scene: each instance's mesh box (from the mesh list) through its
/// transform (row-major 3 x 4), all eight corners.
function sceneBounds(doc) {
  const min = [Infinity, Infinity, Infinity], max = [-Infinity, -Infinity, -Infinity];
  for (const inst of doc.instances) {
    const mesh = state.meshes.find((m) => m.id === inst.mesh);
    if (!mesh) continue;
    const t = inst.transform.flat();
    for (let k = 0; k < 8; ++k) {
      const p = [0, 1, 2].map((a) => ((k >> a) & 1 ? mesh.bounds.max[a] : mesh.bounds.min[a]));
      for (let r = 0; r < 3; ++r) {
        const w = t[4 * r] * p[0] + t[4 * r + 1] * p[1] + t[4 * r + 2] * p[2] + t[4 * r + 3];
        min[r] = Math.min(min[r], w);
        max[r] = Math.max(max[r], w);
      }
    }
  }
  return { min, max };
}

async function openScene(id) {
  try {
    const doc = await api.scene(id);
    if (doc.instances.some((inst) => !state.meshes.some((m) => m.id === inst.mesh))) state.meshes = await api.listMeshes();
    const bounds = sceneBounds(doc);
    if (!(bounds.min[0] <= bounds.max[0])) throw new api.ApiError(0, `scene ${id.slice(0, 12)}: none of its meshes is stored`);
    state.mesh = { id: doc.id, scene: true, bounds, instances: doc.instances.length, revision: doc.revision };
    showError('scene-error', null);
    state.view.frame(bounds);
    renderMeshTable();
    renderSceneTable();
    showBounds();
    viewChanged();
  } catch (e) {
    showError('scene-error', e);
  }
}

$('scene-form').addEventListener('submit', (e) => {
  e.preventDefault();
  const id = $('scene-id').value.trim();
  if (id) openScene(id);
});
$('scenes-refresh').addEventListener('click', refreshScenes);

async function removeMesh(m) {
  try {
    await api.deleteMesh(m.id);
    if (state.mesh && state.mesh.id === m.id) {
      state.mesh = null;
      ctx2d.clearRect(0, 0, canvas.width, canvas.height);
    }
    await refreshMeshes();
  } catch (e) {
    showError('upload-error', e);
  }
}

async function upload(file) {
  const progress = $('upload-progress');
  progress.hidden = false;
  progress.value = 0;
  showError('upload-error', null);
  $('upload-state').textContent = `Uploading ${file.name}…`;
  try {
    const summary = await api.uploadMesh(file, (f) => {
      progress.value = f;
      $('upload-state').textContent = f < 1 ? `Uploading ${file.name}: ${Math.round(f * 100)} %` : `Building the tree of ${file.name}…`;
    });
    $('upload-state').textContent = `${file.name}: ${summary.triangles.toLocaleString('en')} triangles, built in ${summary.build_ms.toFixed(0)} ms`;
    state.mesh = null;
    await refreshMeshes();
    const added = state.meshes.find((m) => m.id === summary.id);
    if (added) selectMesh(added);
  } catch (e) {
    $('upload-state').textContent = `${file.name} was refused`;
    showError('upload-error', new api.ApiError(e.status, `${file.name}: ${e.message}`));
  } finally {
    progress.hidden = true;
  }
}

$('file').addEventListener('change', () => {
  const file = $('file').files[0];
  $('file').value = '';
  if (file) upload(file);
});
const drop = $('drop');
for (const type of ['dragenter', 'dragover']) {
  drop.addEventListener(type, (e) => { e.preventDefault(); drop.classList.add('over'); });
}
drop.addEventListener('dragleave', () => drop.classList.remove('over'));
drop.addEventListener('drop', (e) => {
  e.preventDefault();
  drop.classList.remove('over');
  const file = e.dataTransfer.files[0];
  if (file) upload(file);
});
// A file dropped anywhere else must not make the browser navigate away to it.
window.addEventListener('dragover', (e) => e.preventDefault());
window.addEventListener('drop', (e) => e.preventDefault());

// ---- Rendering -----------------------------------------------------------------------------

async function draw(blob) {
  const bitmap = await createImageBitmap(blob);
  ctx2d.imageSmoothingEnabled = true;
  ctx2d.imageSmoothingQuality = 'high';
  ctx2d.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
  bitmap.close();
}

async function renderFrame(preview) {
  if (!state.mesh || canvas.width === 0) return;
  if (state.inflight) state.inflight.abort();
  const controller = new AbortController();
  state.inflight = controller;
  const generation = state.generation;
  const request = renderRequest({ preview });
  $('view-state').textContent = preview ? 'preview…' : 'rendering…';
  try {
    const { blob, renderMs } = await api.render(request, controller.signal);
    if (generation !== state.generation) return;  // a newer view is on its way
    await draw(blob);
    state.lastRequest = request;
    state.lastBlob = blob;
    state.lastFull = !preview;
    canvas.dataset.frames = String(Number(canvas.dataset.frames || 0) + 1);
    canvas.dataset.full = String(!preview);
    $('view-state').textContent = `${request.width}×${request.height} ${request.shading}, ${request.spp} spp, ${renderMs.toFixed(0)} ms${preview ? ' (preview)' : ''}`;
    showError('view-error', null);
    updateCommand();
  } catch (e) {
    if (e.name !== 'AbortError') {
      $('view-state').textContent = '';
      showError('view-error', e);
    }
  } finally {
    if (state.inflight === controller) state.inflight = null;
  }
}

/// The camera or a setting changed: the frame in flight is stale. A preview at once, the full
/// frame once the view rests.
function viewChanged() {
  state.generation += 1;
  if (state.inflight) state.inflight.abort();
  clearTimeout(state.restTimer);
  if (!state.mesh) return;
  renderFrame(true);
  state.restTimer = setTimeout(() => renderFrame(false), REST_MS);
}

for (const id of ['shading', 'spp', 'ao-samples', 'ao-distance', 'light-azimuth', 'light-elevation', 'sky']) {
  $(id).addEventListener('change', viewChanged);
}
$('light-azimuth').addEventListener('input', viewChanged);
$('light-elevation').addEventListener('input', viewChanged);

// ---- Camera input: mouse, touch, keyboard --------------------------------------------------

const pointers = new Map();
let gesture = null;

canvas.addEventListener('pointerdown', (e) => {
  canvas.setPointerCapture(e.pointerId);
  pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
  const pan = e.button === 1 || e.button === 2 || e.shiftKey;
  gesture = { pan, pinch: pointers.size >= 2 ? pinchOf() : null };
  canvas.focus();
});

function pinchOf() {
  const [a, b] = [...pointers.values()];
  return { d: Math.hypot(a.x - b.x, a.y - b.y), x: (a.x + b.x) / 2, y: (a.y + b.y) / 2 };
}

canvas.addEventListener('pointermove', (e) => {
  const p = pointers.get(e.pointerId);
  if (!p || !gesture) return;
  const dx = e.clientX - p.x, dy = e.clientY - p.y;
  p.x = e.clientX;
  p.y = e.clientY;
  if (pointers.size >= 2) {
    const now = pinchOf();
    if (gesture.pinch && now.d > 0) {
      state.view.zoom(gesture.pinch.d / now.d);
      state.view.pan(now.x - gesture.pinch.x, now.y - gesture.pinch.y, canvas.clientHeight);
    }
    gesture.pinch = now;
  } else if (gesture.pan) {
    state.view.pan(dx, dy, canvas.clientHeight);
  } else {
    state.view.orbit(dx, dy);
  }
  if (dx !== 0 || dy !== 0 || pointers.size >= 2) viewChanged();
});

function endPointer(e) {
  pointers.delete(e.pointerId);
  if (pointers.size === 0) gesture = null;
  else if (gesture) gesture.pinch = pointers.size >= 2 ? pinchOf() : null;
}
canvas.addEventListener('pointerup', endPointer);
canvas.addEventListener('pointercancel', endPointer);
canvas.addEventListener('contextmenu', (e) => e.preventDefault());
canvas.addEventListener('wheel', (e) => {
  e.preventDefault();
  state.view.zoom(Math.exp(e.deltaY * 0.001));
  viewChanged();
}, { passive: false });
canvas.addEventListener('keydown', (e) => {
  const step = 20;
  const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
  if (moves[e.key]) {
    const [dx, dy] = moves[e.key];
    if (e.shiftKey) state.view.pan(dx, dy, canvas.clientHeight);
    else state.view.orbit(dx, dy);
  } else if (e.key === '+' || e.key === '=') {
    state.view.zoom(1 / 1.15);
  } else if (e.key === '-') {
    state.view.zoom(1.15);
  } else if (e.key === 'Home' && state.mesh) {
    state.view.frame(state.mesh.bounds);
  } else {
    return;
  }
  e.preventDefault();
  viewChanged();
});

// The canvas holds as many pixels as the screen shows (devicePixelRatio included).
// devicePixelContentBoxSize is exact on fractional ratios, but some browsers (headless Chromium
// under device emulation) report CSS pixels there: it is used only when it agrees with the ratio.
function fitCanvas(entry) {
  const dpr = window.devicePixelRatio || 1;
  const rect = canvas.getBoundingClientRect();
  let w = Math.round(rect.width * dpr), h = Math.round(rect.height * dpr);
  const box = entry && entry.devicePixelContentBoxSize && entry.devicePixelContentBoxSize[0];
  if (box && Math.abs(box.inlineSize - w) <= 1 && Math.abs(box.blockSize - h) <= 1) {
    w = box.inlineSize;
    h = box.blockSize;
  }
  if (w !== canvas.width || h !== canvas.height) {
    canvas.width = w;
    canvas.height = h;
    viewChanged();
  }
}
new ResizeObserver((entries) => fitCanvas(entries[entries.length - 1])).observe(canvas);
// A window moved to a screen of another pixel ratio (or a browser zoom) resizes no element.
function watchPixelRatio() {
  matchMedia(`(resolution: ${window.devicePixelRatio}dppx)`).addEventListener('change', () => {
    fitCanvas(null);
    watchPixelRatio();
  }, { once: true });
}
watchPixelRatio();

// ---- Export: downloads and command lines ---------------------------------------------------

function save(blob, name) {
  const url = URL.createObjectURL(blob);
  const a = document.createElement('a');
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

function baseName(ext) {
  return `kdrt-${state.mesh.id.slice(0, 8)}-${$('shading').value}.${ext}`;
}

$('download-png').addEventListener('click', async () => {
  if (!state.mesh) return;
  try {
    const blob = state.lastFull && state.lastBlob ? state.lastBlob : (await api.render(renderRequest())).blob;
    save(blob, baseName('png'));
  } catch (e) { showError('view-error', e); }
});
$('download-exr').addEventListener('click', async () => {
  if (!state.mesh) return;
  try {
    save((await api.render(renderRequest({ format: 'exr' }))).blob, baseName('exr'));
  } catch (e) { showError('view-error', e); }
});

function shellQuote(s) { return `'${s.replace(/'/g, "'\\''")}'`; }

function commands(request) {
  const origin = location.origin;
  const auth = api.token() ? ' -H "Authorization: Bearer $KDRT_TOKEN"' : '';
  const route = api.renderRoute(request);
  const curl = `curl -sS --fail-with-body -X POST ${origin}${route.path} -H 'Content-Type: application/json'${auth} \\\n  -d ${shellQuote(JSON.stringify(route.body))} \\\n  -o frame.${request.format}`;
  if (request.scene) return { curl, kdrt: '# kdrt renders meshes only: use the curl line for a scene' };
  const c = request.camera;
  let kdrt = `kdrt --server ${origin}${api.token() ? ' --token "$KDRT_TOKEN"' : ''} render ${request.mesh} -o frame.${request.format} \\\n` +
    `  --size ${request.width}x${request.height} --eye ${c.eye.join(',')} --look-at ${c.look_at.join(',')} ` +
    `--up ${c.up.join(',')} --fov ${c.fov} --shading ${request.shading} --spp ${request.spp}`;
  // The render settings beyond the camera, as kdrt render's flags (only those the request sets).
  const flags = [];
  if ('ao_samples' in request) flags.push(`--ao-samples ${request.ao_samples}`);
  if ('ao_distance' in request) flags.push(`--ao-distance ${request.ao_distance}`);
  if (request.light && request.light.direction) flags.push(`--light ${request.light.direction.join(',')}`);
  if (request.light && 'intensity' in request.light) flags.push(`--light-intensity ${request.light.intensity}`);
  if ('bounces' in request) flags.push(`--bounces ${request.bounces}`);
  if ('sky' in request) flags.push(`--sky ${request.sky}`);
  if ('background' in request) flags.push(`--background ${request.background.join(',')}`);
  if (flags.length) kdrt += ` \\\n  ${flags.join(' ')}`;
  return { curl, kdrt };
}

function updateCommand() {
  if (!state.lastRequest) return;
  const { curl } = commands({ ...state.lastRequest, ...fullSize() });
  $('command').value = curl;
}

function fullSize() {
  const [width, height] = frameSize(1);
  return { width, height, spp: numberInput('spp', 1, 1024, 1) };
}

async function copy(which) {
  if (!state.mesh) return;
  const text = commands(renderRequest())[which];
  $('command').value = text;
  try {
    await navigator.clipboard.writeText(text);
  } catch {
    $('command').select();
    document.execCommand('copy');
  }
  $('view-state').textContent = `${which} command line copied`;
}
$('copy-curl').addEventListener('click', () => copy('curl'));
$('copy-kdrt').addEventListener('click', () => copy('kdrt'));

// ---- Long renders: the async job API -------------------------------------------------------

function showJob(status) {
  $('job-progress').value = status.progress;
  $('job-state').textContent = `job ${status.id.slice(0, 8)}: ${status.state}` +
    (status.state === 'running' || status.state === 'queued' ? ` ${(status.progress * 100).toFixed(0)} %` : '') +
    (status.error ? ` (${status.error})` : '') +
    (status.render_ms !== undefined ? ` in ${(status.render_ms / 1000).toFixed(1)} s` : '');
  $('job-state').dataset.state = status.state;
  $('job-state').dataset.id = status.id;
}

$('job-start').addEventListener('click', async () => {
  if (!state.mesh || state.job) return;
  const side = numberInput('job-size', 16, 8192, 2048);
  const aspect = canvas.width / Math.max(canvas.height, 1);
  const size = aspect >= 1 ? [side, Math.max(1, Math.round(side / aspect))] : [Math.max(1, Math.round(side * aspect)), side];
  const request = renderRequest({ size, spp: numberInput('job-spp', 1, 1024, 64) });
  try {
    const status = await api.submitJob(request);
    state.job = status;
    $('job-start').disabled = true;
    $('job-cancel').disabled = false;
    showJob(status);
    followJob(status.id, request);
  } catch (e) {
    $('job-state').textContent = e.message;
    if (e.status === 401) askForToken(e.message);
  }
});

async function followJob(id, request) {
  for (;;) {
    await new Promise((r) => setTimeout(r, 250));
    let status;
    try {
      status = await api.job(id);
    } catch (e) {
      $('job-state').textContent = e.message;
      break;
    }
    showJob(status);
    if (status.state === 'done') {
      try {
        const blob = await api.jobResult(id);
        state.generation += 1;  // the job's frame replaces the interactive one
        await draw(blob);
        state.lastRequest = request;
        state.lastBlob = blob;
        state.lastFull = true;
        await api.cancelJob(id);  // forget it: the page holds the image now
      } catch (e) {
        $('job-state').textContent = e.message;
      }
      break;
    }
    if (status.state === 'failed' || status.state === 'cancelled') break;
  }
  state.job = null;
  $('job-start').disabled = false;
  $('job-cancel').disabled = true;
}

$('job-cancel').addEventListener('click', async () => {
  if (!state.job) return;
  try {
    const status = await api.cancelJob(state.job.id);
    if (status) showJob(status);
  } catch (e) {
    $('job-state').textContent = e.message;
  }
});

// ---- Status panel --------------------------------------------------------------------------

async function pollStatus() {
  try {
    const m = await api.metrics();
    const info = (m.kdrt_build_info || [])[0];
    if (info) {
      $('st-version').textContent = info.labels.version || '–';
      $('st-isa').textContent = info.labels.isa || '–';
    }
    const threads = (m.kdrt_engine_threads || [])[0];
    if (threads) $('st-threads').textContent = String(threads.value);
    const rays = (m.kdrt_rays_traced_total || []).reduce((sum, s) => sum + s.value, 0);
    const now = performance.now();
    if (state.metricsPrev) {
      const perSecond = (rays - state.metricsPrev.rays) / ((now - state.metricsPrev.t) / 1000);
      $('st-rays').textContent = perSecond >= 1e6 ? `${(perSecond / 1e6).toFixed(1)} M` : perSecond.toFixed(0);
    }
    state.metricsPrev = { rays, t: now };
  } catch {
    $('st-version').textContent = 'unreachable';
  }
}

pollStatus();
setInterval(pollStatus, 2000);
refreshMeshes().then(refreshScenes);
