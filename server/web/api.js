// The kdrt public API (proto/openapi.yaml), as the viewer uses it: same origin only, the bearer
// token from session storage (never local storage, never a cookie).

const TOKEN_KEY = 'kdrt.token';

export function token() {
  return sessionStorage.getItem(TOKEN_KEY) || '';
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/// An answer other than 2xx: status and the problem+json detail when the server sent one.
export class ApiError extends Error {
  constructor(status, detail, problem) {
    super(detail);
    this.status = status;
    this.problem = problem;
  }
}

function authHeaders(headers = {}) {
  const t = token();
  return t ? { ...headers, Authorization: `Bearer ${t}` } : headers;
}

async function problemOf(response) {
  let problem = null;
  const type = response.headers.get('Content-Type') || '';
  if (type.includes('json')) {
    try { problem = await response.json(); } catch { problem = null; }
  }
  const detail = problem && problem.detail ? problem.detail : `${response.status} ${response.statusText}`;
  return new ApiError(response.status, detail, problem);
}

/// fetch with the token; throws ApiError for a non-2xx answer.
export async function call(method, path, { body, headers = {}, signal } = {}) {
  const response = await fetch(path, { method, body, signal, headers: authHeaders(headers), cache: 'no-store' });
  if (!response.ok) throw await problemOf(response);
  return response;
}

export async function listMeshes() {
  return (await (await call('GET', '/v1/meshes')).json()).meshes;
}

export async function deleteMesh(id) {
  await call('DELETE', `/v1/meshes/${encodeURIComponent(id)}`);
}

const FORMATS = ['obj', 'ply', 'off', 'stl', 'raw'];

/// The ?format= of a file name, or null.
export function meshFormat(name) {
  const ext = name.toLowerCase().split('.').pop();
  return FORMATS.includes(ext) ? ext : null;
}

/// POST /v1/meshes with upload progress (fetch reports none, so XMLHttpRequest).
/// onProgress(fraction); resolves to the mesh summary; rejects with ApiError.
export function uploadMesh(file, onProgress) {
  return new Promise((resolve, reject) => {
    const format = meshFormat(file.name);
    if (!format) {
      reject(new ApiError(0, `${file.name}: not a mesh file name (expected .${FORMATS.join(', .')})`));
      return;
    }
    const xhr = new XMLHttpRequest();
    xhr.open('POST', `/v1/meshes?format=${format}`);
    const t = token();
    if (t) xhr.setRequestHeader('Authorization', `Bearer ${t}`);
    xhr.setRequestHeader('Content-Type', 'application/octet-stream');
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
    xhr.onerror = () => reject(new ApiError(0, 'the upload failed (connection lost)'));
    xhr.onload = () => {
      let doc = null;
      try { doc = JSON.parse(xhr.responseText); } catch { doc = null; }
      if (xhr.status >= 200 && xhr.status < 300) resolve(doc);
      else reject(new ApiError(xhr.status, doc && doc.detail ? doc.detail : `${xhr.status} ${xhr.statusText}`, doc));
    };
    xhr.send(file);
  });
}

export async function listScenes() {
  return (await (await call('GET', '/v1/scenes')).json()).scenes;
}

export async function scene(id) {
  return (await call('GET', `/v1/scenes/${encodeURIComponent(id)}`)).json();
}

/// Where a viewer render request goes: POST /v1/render for a mesh; for a scene (the request
/// names `scene` instead of `mesh`) POST /v1/scenes/{id}/render with the request without it.
export function renderRoute(request) {
  if (!request.scene) return { path: '/v1/render', body: request };
  const { scene: id, ...body } = request;
  return { path: `/v1/scenes/${encodeURIComponent(id)}/render`, body };
}

/// POST /v1/render (or a scene's render): resolves to the image Blob.
export async function render(request, signal) {
  const route = renderRoute(request);
  const response = await call('POST', route.path, {
    body: JSON.stringify(route.body),
    headers: { 'Content-Type': 'application/json' },
    signal,
  });
  return { blob: await response.blob(), renderMs: Number(response.headers.get('X-Render-Ms')) };
}

/// POST /v1/render with Prefer: respond-async: resolves to the job status.
export async function submitJob(request) {
  const route = renderRoute(request);
  const response = await call('POST', route.path, {
    body: JSON.stringify(route.body),
    headers: { 'Content-Type': 'application/json', Prefer: 'respond-async' },
  });
  return response.json();
}

export async function job(id) {
  return (await call('GET', `/v1/jobs/${encodeURIComponent(id)}`)).json();
}

export async function cancelJob(id) {
  const response = await call('DELETE', `/v1/jobs/${encodeURIComponent(id)}`);
  return response.status === 204 ? null : response.json();
}

export async function jobResult(id) {
  return (await call('GET', `/v1/jobs/${encodeURIComponent(id)}/result`)).blob();
}

/// GET /metrics (open, no token), parsed into { name: [{labels, value}] }.
export async function metrics() {
  const text = await (await fetch('/metrics', { cache: 'no-store' })).text();
  const out = {};
  for (const line of text.split('\n')) {
    if (!line || line.startsWith('#')) continue;
    const m = /^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(.*)\})?\s+(\S+)/.exec(line);
    if (!m) continue;
    const labels = {};
    if (m[3]) for (const l of m[3].matchAll(/([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"/g)) labels[l[1]] = l[2];
    (out[m[1]] ||= []).push({ labels, value: Number(m[4]) });
  }
  return out;
}
