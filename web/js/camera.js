// Cameras for the web player, with msth-core's conventions (core/src/camera.rs): OpenGL camera
// axes (+X right, +Y up, looking down -Z), `world_from_camera` the camera-to-world matrix
// (column-major, 16 numbers), pixel centres at +0.5. `Rig` is player/src/path.rs's rig, so
// `view:AZ,EL,DIST` means the same viewpoint here as in `msth play --path view:AZ,EL,DIST`.

const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const length = (a) => Math.sqrt(dot(a, a));
const normalize = (a) => mul(a, 1 / length(a));
/** `None` (null) for (near-)zero vectors, as glam's `try_normalize`. */
const tryNormalize = (a) => {
  const l = length(a);
  return l > 0 && Number.isFinite(1 / l) ? mul(a, 1 / l) : null;
};

export const vec3 = { add, sub, mul, dot, cross, length, normalize };

/** A pinhole camera as in the file's metadata. */
export function cameraFromJson(c) {
  return { width: c.width, height: c.height, fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, m: c.world_from_camera.slice() };
}

/** Camera centre (the matrix's fourth column). */
export const center = (cam) => [cam.m[12], cam.m[13], cam.m[14]];

/** A camera with a horizontal field of view, principal point centred. */
export function fromFovX(width, height, fovX, m) {
  const f = (0.5 * width) / Math.tan(0.5 * fovX);
  return { width, height, fx: f, fy: f, cx: 0.5 * width, cy: 0.5 * height, m };
}

/** A camera at `eye` looking at `target`, `up` the approximate up vector. */
export function lookAt(width, height, fovX, eye, target, up) {
  const back = normalize(sub(eye, target));
  const right = normalize(cross(up, back));
  const camUp = cross(back, right);
  return fromFovX(width, height, fovX, [...right, 0, ...camUp, 0, ...back, 0, ...eye, 1]);
}

/** Resizes the image keeping the horizontal field of view and principal point (path.rs `resize`). */
export function resize(cam, width, height) {
  const sx = width / cam.width;
  const sy = height / cam.height;
  return { width, height, fx: cam.fx * sx, fy: cam.fy * sx, cx: cam.cx * sx, cy: cam.cy * sy, m: cam.m };
}

function snapToAxis(v) {
  const axes = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]];
  let best = axes[0];
  for (const a of axes) if (dot(a, v) > dot(best, v)) best = a;
  return dot(best, v) >= Math.cos((30 * Math.PI) / 180) ? best : v;
}

/**
 * The frame free viewpoints turn in (path.rs `Rig::new`): centre, up, horizontal axes `e1`
 * (towards the first camera) and `e2`, mean radius and elevation of the file's cameras, and the
 * intrinsics template (the first camera, resized).
 */
export function makeRig(bounds, cameras, template) {
  let lo;
  let hi;
  let c;
  let forwardFacing;
  if (bounds.kind === "box") {
    lo = bounds.min;
    hi = bounds.max;
    c = mul(add(lo, hi), 0.5);
    forwardFacing = false;
  } else {
    const r = bounds.radius;
    lo = sub(bounds.center, [r, r, r]);
    hi = add(bounds.center, [r, r, r]);
    c = bounds.center.slice();
    forwardFacing = true;
  }
  const ySum = cameras.reduce((s, cam) => add(s, [cam.m[4], cam.m[5], cam.m[6]]), [0, 0, 0]);
  const up = snapToAxis(tryNormalize(ySum) || [0, 0, 1]);
  const offsets = cameras.map((cam) => sub(center(cam), c)).filter((v) => length(v) > 1e-6);
  const radius = offsets.length
    ? offsets.reduce((s, v) => s + length(v), 0) / offsets.length
    : 2 * Math.min(Math.max(length(sub(hi, lo)), 1e-3), 1e3);
  const elevation = offsets.length
    ? offsets.reduce((s, v) => s + Math.asin(Math.min(1, Math.max(-1, dot(normalize(v), up)))), 0) / offsets.length
    : 0.5;
  const horizontal = (v) => tryNormalize(sub(v, mul(up, dot(v, up))));
  const e1 = (offsets.length && horizontal(offsets[0])) || horizontal([1, 0, 0]) || horizontal([0, 1, 0]) || [1, 0, 0];
  const e2 = cross(up, e1);
  return { center: c, up, e1, e2, radius, elevation, forwardFacing, template };
}

/** The camera at azimuth and elevation (radians) and distance, looking at the rig's centre. */
export function rigView(rig, azimuth, elevation, distance, target = rig.center) {
  const dir = add(
    mul(add(mul(rig.e1, Math.cos(azimuth)), mul(rig.e2, Math.sin(azimuth))), Math.cos(elevation)),
    mul(rig.up, Math.sin(elevation)),
  );
  const eye = add(target, mul(dir, distance));
  const cam = lookAt(rig.template.width, rig.template.height, 1.0, eye, target, rig.up);
  const t = rig.template;
  return { ...cam, fx: t.fx, fy: t.fy, cx: t.cx, cy: t.cy };
}

/** The default playback template: the first file camera (or a 256x256 one), resized. */
export function templateCamera(cameras, size) {
  const base = cameras.length ? cameras[0] : fromFovX(256, 256, 0.8, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
  return size ? resize(base, size[0], size[1]) : base;
}

/**
 * Orbit controls state: azimuth/elevation (degrees), distance and a pan offset of the target in
 * the rig's frame. `camera()` gives the current camera; at zero pan it is exactly `rigView`.
 * After `setCamera(cam)` (one of the file's cameras) `camera()` is that camera exactly, and the
 * orbit parameters are set so that the first drag turns about the point of its view axis nearest
 * the scene centre, continuing from its position and viewing direction.
 */
export class Orbit {
  constructor(rig, az = 0, el = (rig.elevation * 180) / Math.PI, dist = rig.radius) {
    this.rig = rig;
    this.az = az;
    this.el = el;
    this.dist = dist;
    this.pan = [0, 0, 0];
    /** A file camera shown as it is until the first orbit, pan or zoom (null: the orbit's view). */
    this.fixed = null;
  }
  /** Shows `cam` (resized to the rig's template) and continues orbiting from it. */
  setCamera(cam) {
    const rig = this.rig;
    const t = rig.template;
    this.fixed = cam.width === t.width && cam.height === t.height ? cam : resize(cam, t.width, t.height);
    const eye = center(cam);
    const forward = normalize([-cam.m[8], -cam.m[9], -cam.m[10]]);
    const along = Math.max(dot(sub(rig.center, eye), forward), 0.05 * rig.radius);
    const target = add(eye, mul(forward, along));
    const d = sub(eye, target);
    this.pan = sub(target, rig.center);
    this.dist = length(d);
    this.el = (Math.asin(Math.min(1, Math.max(-1, dot(d, rig.up) / this.dist))) * 180) / Math.PI;
    this.az = (Math.atan2(dot(d, rig.e2), dot(d, rig.e1)) * 180) / Math.PI;
  }
  camera() {
    if (this.fixed) return this.fixed;
    const target = add(this.rig.center, this.pan);
    return rigView(this.rig, (this.az * Math.PI) / 180, (this.el * Math.PI) / 180, this.dist, target);
  }
  /** Turns by a drag of (dx, dy) pixels. */
  rotate(dx, dy) {
    this.fixed = null;
    this.az -= dx * 0.4;
    this.el = Math.min(89, Math.max(-89, this.el + dy * 0.4));
  }
  /** Moves the target by a drag of (dx, dy) pixels in the image plane. */
  panBy(dx, dy) {
    this.fixed = null;
    const cam = this.camera();
    const right = [cam.m[0], cam.m[1], cam.m[2]];
    const upv = [cam.m[4], cam.m[5], cam.m[6]];
    const k = this.dist / cam.fx;
    this.pan = add(this.pan, add(mul(right, -dx * k), mul(upv, dy * k)));
  }
  /** Zooms by a factor (> 1 moves away). */
  zoom(factor) {
    this.fixed = null;
    this.dist = Math.min(this.rig.radius * 20, Math.max(this.rig.radius * 0.05, this.dist * factor));
  }
}
