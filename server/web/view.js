// The orbit camera: a target point, a distance and two angles; turned into the render request's
// camera (eye, look_at, up, fov).

const DEG = Math.PI / 180;

function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
function scale(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function normalize(a) { const l = Math.hypot(a[0], a[1], a[2]) || 1; return scale(a, 1 / l); }

export class OrbitView {
  constructor() {
    this.fov = 40;
    this.frame({ min: [-1, -1, -1], max: [1, 1, 1] });
  }

  /// Frames a mesh's bounds from the front, a little above and to the right (like the
  /// server's default view).
  frame(bounds) {
    this.target = scale(add(bounds.min, bounds.max), 0.5);
    const d = [0, 1, 2].map((i) => bounds.max[i] - bounds.min[i]);
    this.radius = Math.max(0.5 * Math.hypot(d[0], d[1], d[2]), 1e-6);
    this.distance = (this.radius * 1.05) / Math.sin(0.5 * this.fov * DEG);
    this.yaw = 19 * DEG;
    this.pitch = 14 * DEG;
  }

  /// From the target towards the eye (unit).
  back() {
    const c = Math.cos(this.pitch);
    return [c * Math.sin(this.yaw), Math.sin(this.pitch), c * Math.cos(this.yaw)];
  }

  basis() {
    const back = this.back();
    const right = normalize(cross([0, 1, 0], back));
    const up = cross(back, right);
    return { back, right, up };
  }

  orbit(dx, dy) {
    this.yaw -= dx * 0.01;
    this.pitch = Math.max(-89 * DEG, Math.min(89 * DEG, this.pitch + dy * 0.01));
  }

  /// dx, dy in pixels of a view `height` pixels tall: the target follows the pointer.
  pan(dx, dy, height) {
    const { right, up } = this.basis();
    const perPixel = (2 * this.distance * Math.tan(0.5 * this.fov * DEG)) / Math.max(height, 1);
    this.target = add(this.target, add(scale(right, -dx * perPixel), scale(up, dy * perPixel)));
  }

  /// factor > 1 moves away.
  zoom(factor) {
    this.distance = Math.min(Math.max(this.distance * factor, this.radius * 0.05), this.radius * 100);
  }

  camera() {
    const eye = add(this.target, scale(this.back(), this.distance));
    return { eye: eye.map(round), look_at: this.target.map(round), up: [0, 1, 0], fov: this.fov };
  }

  /// A direction towards the light: `azimuth` degrees around the view's up axis from the camera
  /// side (0 = from behind the camera, positive = from the right), `elevation` above the view.
  lightDirection(azimuth, elevation) {
    const { back, right, up } = this.basis();
    const a = azimuth * DEG, e = elevation * DEG;
    const d = add(add(scale(back, Math.cos(e) * Math.cos(a)), scale(right, Math.cos(e) * Math.sin(a))), scale(up, Math.sin(e)));
    return normalize(d).map(round);
  }
}

/// Six significant digits: short request bodies and command lines, far below what a view needs.
function round(v) { return Number(v.toPrecision(6)); }
