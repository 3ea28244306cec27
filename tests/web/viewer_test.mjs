// The web viewer in a real browser: Debian's chromium driven by playwright-core against real
// kdrt-server processes on ephemeral ports (tests/web/README.md). Registered with ctest as
// web_viewer (label integration); scripts/test installs playwright-core with `npm ci`.
//
//   node viewer_test.mjs --server PATH/kdrt-server --kdrt PATH/kdrt --data tests/data --modules DIR/node_modules
//                        --out DIR/artifacts [--chromium /usr/bin/chromium]
//
// Every step saves a screenshot under --out. Exits 0 when every check passed, 1 otherwise.

import { execSync, spawn } from 'node:child_process';
import { createRequire } from 'node:module';
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import assert from 'node:assert/strict';

function options() {
  const out = { chromium: '/usr/bin/chromium' };
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i += 2) out[argv[i].replace(/^--/, '')] = argv[i + 1];
  for (const need of ['server', 'kdrt', 'data', 'modules', 'out']) {
    if (!out[need]) throw new Error(`missing --${need}`);
  }
  for (const file of ['server', 'kdrt', 'data', 'modules', 'out']) out[file] = path.resolve(out[file]);
  return out;
}

const opt = options();
if (!fs.existsSync(path.join(opt.modules, 'playwright-core'))) {
  console.error(`playwright-core is not installed in ${opt.modules}: run \`npm ci\` in ${path.dirname(opt.modules)} (scripts/test does)`);
  process.exit(1);
}
const { chromium } = createRequire(path.resolve(opt.modules, 'index.js'))('playwright-core');

fs.rmSync(opt.out, { recursive: true, force: true });
fs.mkdirSync(opt.out, { recursive: true });
const scratch = fs.mkdtempSync(path.join(os.tmpdir(), 'kdrt-web-'));
const children = [];

function log(...args) { console.log(`[${(performance.now() / 1000).toFixed(1)} s]`, ...args); }

/// Starts kdrt-server on an ephemeral port; resolves to { origin, process, log }.
async function startServer(name, extraEnv = {}) {
  const dir = path.join(scratch, name);
  fs.mkdirSync(dir);
  const portFile = path.join(dir, 'port');
  const logFile = path.join(dir, 'server.log');
  const child = spawn(opt.server, ['--listen', '127.0.0.1:0', '--port-file', portFile, '--cache-dir', path.join(dir, 'cache'), '--threads', '2', '--log-level', 'warn'], {
    env: { ...process.env, ...extraEnv },
    stdio: ['ignore', 'ignore', fs.openSync(logFile, 'w')],
  });
  children.push(child);
  const deadline = Date.now() + 20000;
  while (Date.now() < deadline) {
    if (child.exitCode !== null) throw new Error(`kdrt-server exited (${child.exitCode}): ${fs.readFileSync(logFile, 'utf8')}`);
    if (fs.existsSync(portFile)) {
      const port = fs.readFileSync(portFile, 'utf8').trim();
      if (port) {
        const origin = `http://127.0.0.1:${port}`;
        try {
          if ((await fetch(`${origin}/readyz`)).ok) return { origin, child, logFile };
        } catch { /* not listening yet */ }
      }
    }
    await new Promise((r) => setTimeout(r, 50));
  }
  throw new Error('kdrt-server did not become ready in 20 s');
}

const failures = [];

/// Opens a browser context that records console errors and every request's host.
async function openBrowser(name, origin, deviceScaleFactor = 1) {
  const profile = fs.mkdtempSync(path.join(scratch, `profile-${name}-`));
  const context = await chromium.launchPersistentContext(profile, {
    executablePath: opt.chromium,
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-background-networking', '--disable-component-update',
      '--no-first-run', '--disable-sync', '--disable-quic'],
    viewport: { width: 1100, height: 720 },
    deviceScaleFactor,
    acceptDownloads: true,
  });
  const page = context.pages()[0] || await context.newPage();
  const record = { consoleErrors: [], foreign: [], expectedStatuses: new Set() };
  page.on('console', (msg) => {
    const text = msg.text();
    if (msg.type() === 'warning') log(`  console warning: ${text}`);
    if (msg.type() !== 'error') return;
    // Chromium reports every non-2xx answer on the console; the refusals a step provokes on
    // purpose (a 422 upload, the 401 before the token) are allowed, nothing else.
    const m = /the server responded with a status of (\d+)/.exec(text);
    if (m && record.expectedStatuses.has(Number(m[1]))) return;
    record.consoleErrors.push(`${msg.type()}: ${text} (${msg.location().url})`);
  });
  page.on('pageerror', (e) => record.consoleErrors.push(`page error: ${e.message}`));
  context.on('request', (req) => {
    const url = req.url();
    if (!url.startsWith(`${origin}/`) && !url.startsWith('data:') && !url.startsWith('blob:')) record.foreign.push(url);
  });
  return { context, page, record };
}

let stepNumber = 0;
async function step(page, name, fn) {
  stepNumber += 1;
  const label = `${String(stepNumber).padStart(2, '0')}-${name}`;
  log(`step ${label}`);
  try {
    await fn();
    log(`  ok`);
  } catch (e) {
    failures.push(`${label}: ${e.message}`);
    log(`  FAILED: ${e.stack || e.message}`);
  } finally {
    try { await page.screenshot({ path: path.join(opt.out, `${label}.png`) }); } catch (e) { log(`  no screenshot: ${e.message}`); }
  }
}

/// Statistics of the canvas pixels: mean and standard deviation of the luminance, the share of
/// pixels that differ from the corner (background) colour, and a hash of all pixels.
function canvasStats(page) {
  return page.evaluate(() => {
    const c = document.getElementById('view');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let sum = 0, sum2 = 0, differ = 0, hash = 2166136261;
    const bg = [d[0], d[1], d[2]];
    const n = d.length / 4;
    for (let i = 0; i < d.length; i += 4) {
      const y = 0.2126 * d[i] + 0.7152 * d[i + 1] + 0.0722 * d[i + 2];
      sum += y;
      sum2 += y * y;
      if (Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]) > 6) differ += 1;
      hash = Math.imul(hash ^ d[i] ^ (d[i + 1] << 8) ^ (d[i + 2] << 16), 16777619) >>> 0;
    }
    const mean = sum / n;
    return { width: c.width, height: c.height, mean, sd: Math.sqrt(Math.max(0, sum2 / n - mean * mean)), foreground: differ / n, hash, bg };
  });
}

/// Waits for a full-resolution frame newer than `frames` frames.
async function fullFrameAfter(page, frames, timeout = 30000) {
  await page.waitForFunction((f) => {
    const c = document.getElementById('view');
    return Number(c.dataset.frames || 0) > f && c.dataset.full === 'true';
  }, frames, { timeout });
}
const frameCount = (page) => page.evaluate(() => Number(document.getElementById('view').dataset.frames || 0));

function assertNotBlank(s, what) {
  assert.ok(s.foreground > 0.05, `${what}: only ${(s.foreground * 100).toFixed(1)} % of the pixels differ from the background`);
  assert.ok(s.sd > 8, `${what}: luminance sd ${s.sd.toFixed(1)} (a flat image)`);
}

async function changedShare(page, before) {
  // The share of pixels that differ from a snapshot taken with snapshot().
  return page.evaluate(() => {
    const c = document.getElementById('view');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    const old = window.__snapshot;
    let changed = 0;
    for (let i = 0; i < d.length; i += 4) if (Math.abs(d[i] - old[i]) + Math.abs(d[i + 1] - old[i + 1]) + Math.abs(d[i + 2] - old[i + 2]) > 6) changed += 1;
    return changed / (d.length / 4);
  }, before);
}
const snapshot = (page) => page.evaluate(() => {
  const c = document.getElementById('view');
  window.__snapshot = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
});

const bunny = path.join(opt.data, 'bunny00.off');
const badObj = path.join(scratch, 'broken.obj');
fs.writeFileSync(badObj, 'v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n');

async function main() {
  // ---- An open server -------------------------------------------------------------------
  const server = await startServer('open');
  log(`server at ${server.origin}`);
  {
    // The page's own headers, checked from outside the browser.
    const r = await fetch(`${server.origin}/`);
    const csp = r.headers.get('content-security-policy') || '';
    assert.equal(r.status, 200);
    assert.match(r.headers.get('content-type'), /^text\/html/);
    assert.match(csp, /script-src 'self'/);
    assert.doesNotMatch(csp, /unsafe-inline|unsafe-eval/);
    const js = await fetch(`${server.origin}/ui/viewer.js`);
    assert.match(js.headers.get('content-type'), /^text\/javascript/);
    const again = await fetch(`${server.origin}/ui/viewer.js`, { headers: { 'If-None-Match': js.headers.get('etag') } });
    assert.equal(again.status, 304);
  }
  const { context, page, record } = await openBrowser('open', server.origin);
  await page.goto(`${server.origin}/`);

  await step(page, 'upload-bunny', async () => {
    await page.setInputFiles('#file', bunny);
    await page.waitForSelector('#meshes tbody tr', { timeout: 30000 });
    const row = await page.textContent('#meshes tbody tr');
    assert.match(row, /75,408/, `the mesh list row ${JSON.stringify(row)} lacks the bunny's 75,408 triangles`);
    assert.match(await page.textContent('#upload-state'), /75,408 triangles/);
  });

  await step(page, 'labelled-controls', async () => {
    // Every control has an accessible name and can take the keyboard focus.
    const unlabelled = await page.evaluate(() => [...document.querySelectorAll('input, select, textarea, button, canvas')]
      .filter((el) => !((el.labels && el.labels.length) || el.getAttribute('aria-label') || (el.tagName === 'BUTTON' && el.textContent.trim())) || el.tabIndex < 0)
      .map((el) => el.id || el.outerHTML.slice(0, 60)));
    assert.deepEqual(unlabelled, []);
  });

  await step(page, 'first-frame', async () => {
    await fullFrameAfter(page, 0);
    const dims = await page.evaluate(() => { const c = document.getElementById('view'); return [c.width, c.clientWidth, devicePixelRatio]; });
    assert.equal(dims[0], Math.round(dims[1] * dims[2]), `canvas ${dims[0]} px for ${dims[1]} CSS px at ratio ${dims[2]}`);
    const s = await canvasStats(page);
    log(`  frame ${s.width}x${s.height}: mean ${s.mean.toFixed(1)}, sd ${s.sd.toFixed(1)}, foreground ${(s.foreground * 100).toFixed(1)} %, background ${s.bg}`);
    assertNotBlank(s, 'first frame');
    // The background is the viewer's grey, not black.
    assert.ok(s.bg[0] > 40 && s.bg[0] < 90, `background level ${s.bg[0]}`);
  });

  await step(page, 'drag-orbit', async () => {
    await snapshot(page);
    const frames = await frameCount(page);
    const box = await page.locator('#view').boundingBox();
    const x = box.x + box.width / 2, y = box.y + box.height / 2;
    await page.mouse.move(x, y);
    await page.mouse.down();
    for (let i = 1; i <= 10; ++i) await page.mouse.move(x + i * 15, y + i * 4);
    await page.mouse.up();
    await fullFrameAfter(page, frames);
    const changed = await changedShare(page);
    log(`  ${(changed * 100).toFixed(1)} % of the pixels changed`);
    assert.ok(changed > 0.02, `a drag changed only ${(changed * 100).toFixed(2)} % of the pixels`);
    assertNotBlank(await canvasStats(page), 'orbited frame');
  });

  await step(page, 'keyboard-orbit', async () => {
    await snapshot(page);
    const frames = await frameCount(page);
    await page.focus('#view');
    for (let i = 0; i < 4; ++i) await page.keyboard.press('ArrowLeft');
    await fullFrameAfter(page, frames);
    const changed = await changedShare(page);
    assert.ok(changed > 0.02, `arrow keys changed only ${(changed * 100).toFixed(2)} % of the pixels`);
  });

  await step(page, 'ambient-occlusion', async () => {
    await snapshot(page);
    const frames = await frameCount(page);
    await page.fill('#spp', '1');
    await page.selectOption('#shading', 'ao');
    await fullFrameAfter(page, frames);
    const changed = await changedShare(page);
    const s = await canvasStats(page);
    log(`  ao: ${(changed * 100).toFixed(1)} % changed, mean ${s.mean.toFixed(1)}, sd ${s.sd.toFixed(1)}`);
    assert.ok(changed > 0.02, `switching to ao changed only ${(changed * 100).toFixed(2)} % of the pixels`);
    assertNotBlank(s, 'ao frame');
    assert.equal(await page.evaluate(() => document.getElementById('view-error').hidden), true);
  });

  await step(page, 'diffuse-sun-and-sky', async () => {
    await snapshot(page);
    const frames = await frameCount(page);
    await page.selectOption('#shading', 'diffuse');
    await fullFrameAfter(page, frames);
    const changed = await changedShare(page);
    const s = await canvasStats(page);
    log(`  diffuse: ${(changed * 100).toFixed(1)} % changed, mean ${s.mean.toFixed(1)}, sd ${s.sd.toFixed(1)}`);
    assert.ok(changed > 0.02, `switching to diffuse changed only ${(changed * 100).toFixed(2)} % of the pixels`);
    assertNotBlank(s, 'diffuse frame');
  });

  await step(page, 'export-and-commands', async () => {
    // 4 spp for the downloads (and for the README's picture of this step).
    const frames = await frameCount(page);
    await page.fill('#spp', '4');
    await page.dispatchEvent('#spp', 'change');
    await fullFrameAfter(page, frames);
    const dir = fs.mkdtempSync(path.join(scratch, 'export-'));
    const [png] = await Promise.all([page.waitForEvent('download'), page.click('#download-png')]);
    const pngPath = path.join(dir, 'downloaded.png');
    await png.saveAs(pngPath);
    const pngBytes = fs.readFileSync(pngPath);
    assert.equal(pngBytes.subarray(1, 4).toString(), 'PNG');
    const [exr] = await Promise.all([page.waitForEvent('download'), page.click('#download-exr')]);
    assert.match(exr.suggestedFilename(), /\.exr$/);
    const exrPath = path.join(dir, 'downloaded.exr');
    await exr.saveAs(exrPath);
    assert.equal(fs.readFileSync(exrPath).readUInt32LE(0), 20000630, 'the EXR magic number');

    // The copied curl line, run as it is, gives the same bytes as the downloaded frame.
    await page.click('#copy-curl');
    const curl = await page.inputValue('#command');
    assert.ok(curl.startsWith(`curl -sS --fail-with-body -X POST ${server.origin}/v1/render`), curl);
    execSync(curl, { cwd: dir, shell: '/bin/bash', stdio: ['ignore', 'ignore', 'pipe'] });
    assert.ok(fs.readFileSync(path.join(dir, 'frame.png')).equals(pngBytes), 'curl gave other bytes than the download');

    // The kdrt line, run as it is, gives the same bytes too (light, sky and background included).
    await page.click('#copy-kdrt');
    const kdrt = (await page.inputValue('#command')).replace(/^kdrt /, `${opt.kdrt} `);
    assert.match(kdrt, /render [0-9a-f]{64} -o frame\.png/);
    assert.match(kdrt, /--light [-0-9.e,]+ --light-intensity/);
    fs.rmSync(path.join(dir, 'frame.png'));
    execSync(kdrt, { cwd: dir, shell: '/bin/bash', stdio: ['ignore', 'ignore', 'pipe'] });
    assert.ok(fs.readFileSync(path.join(dir, 'frame.png')).equals(pngBytes), 'kdrt render gave other bytes than the download');
    fs.copyFileSync(pngPath, path.join(opt.out, 'frame-diffuse.png'));
  });

  await step(page, 'malformed-obj', async () => {
    record.expectedStatuses.add(422);
    await page.setInputFiles('#file', badObj);
    await page.waitForSelector('#upload-error:not([hidden])', { timeout: 15000 });
    const text = await page.textContent('#upload-error');
    log(`  shown: ${text}`);
    assert.match(text, /broken\.obj: line 4: .*9/, `the page shows ${JSON.stringify(text)}`);
    record.expectedStatuses.delete(422);
  });

  await step(page, 'cancel-long-render', async () => {
    await page.fill('#job-size', '2048');
    await page.fill('#job-spp', '256');
    await page.click('#job-start');
    await page.waitForFunction(() => ['queued', 'running'].includes(document.getElementById('job-state').dataset.state), null, { timeout: 15000 });
    const id = await page.evaluate(() => document.getElementById('job-state').dataset.id);
    await page.click('#job-cancel');
    await page.waitForFunction(() => document.getElementById('job-state').dataset.state === 'cancelled', null, { timeout: 30000 });
    const status = await (await fetch(`${server.origin}/v1/jobs/${id}`)).json();
    assert.equal(status.state, 'cancelled', `the server says the job is ${status.state}`);
    assert.match(await page.textContent('#job-state'), /cancelled/);
  });

  await step(page, 'status-panel', async () => {
    await page.waitForFunction(() => document.getElementById('st-rays').textContent !== '–', null, { timeout: 10000 });
    const isa = await page.textContent('#st-isa');
    const threads = await page.textContent('#st-threads');
    assert.match(isa, /^(scalar|sse4|avx2|avx512)$/);
    assert.equal(threads, '2');
    assert.match(await page.textContent('#st-version'), /^\d+\.\d+/);
  });

  await step(page, 'scene-geomid', async () => {
    // Two bunnies side by side, made through the API; opened from the page's scene list.
    const meshes = (await (await fetch(`${server.origin}/v1/meshes`)).json()).meshes;
    const bunnyMesh = meshes.find((m) => m.triangles === 75408);
    assert.ok(bunnyMesh, 'the bunny is stored');
    const dx = 1.3 * (bunnyMesh.bounds.max[0] - bunnyMesh.bounds.min[0]);
    const created = await fetch(`${server.origin}/v1/scenes`, {
      method: 'POST',
      headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ instances: [
        { mesh: bunnyMesh.id, name: 'left' },
        { mesh: bunnyMesh.id, transform: [1, 0, 0, dx, 0, 1, 0, 0, 0, 0, 1, 0], name: 'right' }] }),
    });
    assert.equal(created.status, 201, await created.clone().text());
    const sceneId = (await created.json()).id;
    let frames = await frameCount(page);
    await page.click('#scenes-refresh');
    await page.click(`button[aria-label="View scene ${sceneId.slice(0, 12)}"]`, { timeout: 10000 });
    await fullFrameAfter(page, frames);
    assert.match(await page.textContent('#mesh-bounds'), /2 instances/);
    frames = await frameCount(page);
    await page.selectOption('#shading', 'geomid');
    await fullFrameAfter(page, frames);
    assert.equal(await page.evaluate(() => document.getElementById('view-error').hidden), true);
    // The frame is the server's: the page's PNG equals the scene route's answer for the request
    // the page shows (its curl line), and the canvas holds that PNG's pixels.
    const curl = await page.inputValue('#command');
    assert.ok(curl.includes(`/v1/scenes/${sceneId}/render`), curl);
    const body = /-d '([^']*)'/.exec(curl)[1];
    assert.ok(!JSON.parse(body).mesh && JSON.parse(body).shading === 'geomid', body);
    const served = Buffer.from(await (await fetch(`${server.origin}/v1/scenes/${sceneId}/render`, {
      method: 'POST', headers: { 'Content-Type': 'application/json' }, body,
    })).arrayBuffer());
    assert.equal(served.subarray(1, 4).toString(), 'PNG');
    const [download] = await Promise.all([page.waitForEvent('download'), page.click('#download-png')]);
    const downloaded = fs.readFileSync(await download.path());
    assert.ok(downloaded.equals(served), 'the page\'s frame is not the server\'s PNG');
    const compared = await page.evaluate(async (b64) => {
      const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
      const bitmap = await createImageBitmap(new Blob([bytes], { type: 'image/png' }));
      const view = document.getElementById('view');
      const off = new OffscreenCanvas(bitmap.width, bitmap.height);
      off.getContext('2d').drawImage(bitmap, 0, 0);
      const want = off.getContext('2d').getImageData(0, 0, bitmap.width, bitmap.height).data;
      const got = view.getContext('2d').getImageData(0, 0, view.width, view.height).data;
      let differ = 0;
      for (let i = 0; i < want.length; ++i) differ += want[i] !== got[i];
      // The most common colour of each half that is not the background (corner) colour.
      const bg = `${got[0]},${got[1]},${got[2]}`;
      const halves = [new Map(), new Map()];
      for (let y = 0; y < view.height; ++y) {
        for (let x = 0; x < view.width; ++x) {
          const i = 4 * (y * view.width + x);
          const c = `${got[i]},${got[i + 1]},${got[i + 2]}`;
          if (c === bg) continue;
          const h = halves[x < view.width / 2 ? 0 : 1];
          h.set(c, (h.get(c) || 0) + 1);
        }
      }
      const top = (h) => [...h.entries()].sort((a, b) => b[1] - a[1])[0] || ['', 0];
      return { size: [bitmap.width, bitmap.height, view.width, view.height], differ, left: top(halves[0]), right: top(halves[1]), pixels: view.width * view.height };
    }, served.toString('base64'));
    log(`  geomid: left ${compared.left[0]} (${compared.left[1]} px), right ${compared.right[0]} (${compared.right[1]} px), ${compared.differ} bytes differ from the server's PNG`);
    assert.deepEqual(compared.size.slice(0, 2), compared.size.slice(2), 'the PNG is the canvas size');
    assert.equal(compared.differ, 0, 'canvas pixels differ from the server\'s PNG');
    // Each instance fills a good part of its half in one flat colour, and the two differ.
    assert.ok(compared.left[1] > 0.02 * compared.pixels && compared.right[1] > 0.02 * compared.pixels, JSON.stringify(compared));
    assert.notEqual(compared.left[0], compared.right[0], 'both instances have one colour');
    const removed = await fetch(`${server.origin}/v1/scenes/${sceneId}`, { method: 'DELETE' });
    assert.ok(removed.ok, `DELETE scene: ${removed.status}`);
  });

  await step(page, 'delete-mesh', async () => {
    await page.click('#meshes tbody tr button[aria-label^="Delete"]');
    await page.waitForSelector('#meshes-empty:not([hidden])', { timeout: 10000 });
    const list = await (await fetch(`${server.origin}/v1/meshes`)).json();
    assert.equal(list.meshes.length, 0);
  });

  assert.deepEqual(record.consoleErrors, [], 'console errors');
  assert.deepEqual(record.foreign, [], 'requests to other hosts');
  await context.close();

  // ---- A token-protected server ---------------------------------------------------------
  const secured = await startServer('token', { KDRT_TOKEN: 's3cret-token' });
  // A high-DPI screen this time: the canvas holds twice the CSS pixels each way.
  const t = await openBrowser('token', secured.origin, 2);
  t.record.expectedStatuses.add(401);
  await t.page.goto(`${secured.origin}/`);
  await step(t.page, 'token-asked', async () => {
    await t.page.waitForFunction(() => /needs a bearer token/.test(document.getElementById('token-state').textContent), null, { timeout: 10000 });
    assert.equal(await t.page.evaluate(() => document.activeElement.id), 'token');
  });
  t.record.expectedStatuses.delete(401);
  await step(t.page, 'token-works', async () => {
    await t.page.fill('#token', 's3cret-token');
    await t.page.click('#token-save');
    await t.page.setInputFiles('#file', bunny);
    await t.page.waitForSelector('#meshes tbody tr', { timeout: 30000 });
    await fullFrameAfter(t.page, 0);
    const s = await canvasStats(t.page);
    assertNotBlank(s, 'frame with a token');
    const css = await t.page.evaluate(() => document.getElementById('view').clientWidth);
    assert.equal(s.width, css * 2, `canvas ${s.width} px for ${css} CSS px at ratio 2`);
    const stored = await t.page.evaluate(() => ({ session: sessionStorage.getItem('kdrt.token'), local: localStorage.length, cookies: document.cookie }));
    assert.deepEqual(stored, { session: 's3cret-token', local: 0, cookies: '' });
  });
  assert.deepEqual(t.record.consoleErrors, [], 'console errors (token server)');
  assert.deepEqual(t.record.foreign, [], 'requests to other hosts (token server)');
  await t.context.close();
}

try {
  await main();
} catch (e) {
  failures.push(e.stack || e.message);
}
for (const child of children) child.kill('SIGTERM');
fs.rmSync(scratch, { recursive: true, force: true });
if (failures.length) {
  console.error(`FAILED (${failures.length}):\n  ${failures.join('\n  ')}\nscreenshots: ${opt.out}`);
  process.exit(1);
}
log(`all ${stepNumber} steps passed; screenshots in ${opt.out}`);
