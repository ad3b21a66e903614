// The orbit camera: a capture camera's intrinsics at an eye that turns around the avatar (drag), and zooms (wheel).

function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
function unit(a) { const n = Math.hypot(...a); return a.map(v => v / n); }
function scale(a, s) { return a.map(v => v * s); }

// Rotate v about the unit axis k by angle t (Rodrigues).
function rotate(v, k, t) {
  const c = Math.cos(t), s = Math.sin(t), kv = cross(k, v), d = dot(k, v);
  return [0, 1, 2].map(i => v[i] * c + kv[i] * s + k[i] * d * (1 - c));
}

// world_to_cam (4 x 4 rows) of a camera at eye looking at target, image y along -up (deliffas.io.cameras.look_at).
export function lookAt(eye, target, up) {
  const z = unit(sub(target, eye));
  const x = unit(cross(scale(up, -1), z));
  const y = cross(z, x);
  const R = [x, y, z];
  return R.map(r => [...r, -dot(r, eye)]).concat([[0, 0, 0, 1]]);
}

// The camera centre -R^T t of a world_to_cam.
export function cameraCenter(E) {
  return [0, 1, 2].map(j => -(E[0][j] * E[0][3] + E[1][j] * E[1][3] + E[2][j] * E[2][3]));
}

export class OrbitCamera {
  constructor(base, target) {
    this.base = base;
    this.target = target;
    this.up = scale(base.world_to_cam[1].slice(0, 3), -1);  // the base camera's image up, in the world
    this.offset = sub(cameraCenter(base.world_to_cam), target);
  }

  drag(dx, dy) {
    let o = rotate(this.offset, unit(this.up), -dx * 0.01);
    const right = unit(cross(o, this.up));
    const tilted = rotate(o, right, dy * 0.01);
    if (Math.abs(dot(unit(tilted), unit(this.up))) < 0.98) o = tilted;
    this.offset = o;
  }

  zoom(factor) { this.offset = scale(this.offset, factor); }

  camera() {
    const eye = this.target.map((t, i) => t + this.offset[i]);
    return {name: 'orbit', K: this.base.K, width: this.base.width, height: this.base.height,
            world_to_cam: lookAt(eye, this.target, this.up)};
  }
}
