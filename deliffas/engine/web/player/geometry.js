// Per-frame geometry on the CPU, in double precision as deliffas computes it: posing (LBS or DQS from the
// motion's bone transforms, SMPL's posing (smpl.js), or the motion's posed vertices), vertex normals, the outer
// shell and the normal maps.

import {SMPLPoser} from './smpl.js';

const ZERO_NORMAL_EPS = 1e-12;  // deliffas.geometry.mesh_ops.ZERO_NORMAL_EPS
const NORMAL_EPS2 = 1e-16;      // deliffas.geometry.normal_maps.NORMAL_EPS ** 2

// (3, 3) rotation part of a 3 x 4 row-major block -> unit quaternion (w, x, y, z) with w >= 0 (skinning.py).
function matrixToQuaternion(m) {
  const [m00, m01, m02, , m10, m11, m12, , m20, m21, m22] = m;
  const tr = m00 + m11 + m22;
  const cand = [[1 + tr, m21 - m12, m02 - m20, m10 - m01],
                [m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20],
                [m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21],
                [m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22]];
  const diag = [1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22];
  let best = 0;
  for (let i = 1; i < 4; i++) if (diag[i] > diag[best]) best = i;
  const q = cand[best];
  const n = Math.hypot(q[0], q[1], q[2], q[3]);
  const s = q[0] / n < 0 ? -1 : 1;
  return q.map(v => s * v / n);
}

function qmul(a, b) {
  return [a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
          a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
          a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
          a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]];
}

function lbs(rest, idx, w, K, bones, off, out) {
  const V = rest.length / 3, M = new Float64Array(12);
  for (let v = 0; v < V; v++) {
    M.fill(0);
    for (let k = 0; k < K; k++) {
      const b = idx[v * K + k];
      if (b < 0) continue;
      const wk = w[v * K + k], o = off + b * 12;
      for (let i = 0; i < 12; i++) M[i] += wk * bones[o + i];
    }
    const x = rest[3 * v], y = rest[3 * v + 1], z = rest[3 * v + 2];
    for (let r = 0; r < 3; r++) out[3 * v + r] = M[4 * r] * x + M[4 * r + 1] * y + M[4 * r + 2] * z + M[4 * r + 3];
  }
}

function dqs(rest, idx, w, K, bones, off, numBones, out) {
  const real = [], dual = [];
  for (let b = 0; b < numBones; b++) {
    const m = bones.subarray(off + b * 12, off + b * 12 + 12);
    const r = matrixToQuaternion(m);
    real.push(r);
    dual.push(qmul([0, m[3], m[7], m[11]], r).map(v => 0.5 * v));
  }
  for (let v = 0; v < rest.length / 3; v++) {
    const br = [0, 0, 0, 0], bd = [0, 0, 0, 0];
    const r0 = real[Math.max(idx[v * K], 0)];
    for (let k = 0; k < K; k++) {
      const b = idx[v * K + k], wk = b >= 0 ? w[v * K + k] : 0, bb = Math.max(b, 0);
      const r = real[bb], d = dual[bb];
      const sign = r[0] * r0[0] + r[1] * r0[1] + r[2] * r0[2] + r[3] * r0[3] < 0 ? -1 : 1;
      for (let i = 0; i < 4; i++) { br[i] += wk * sign * r[i]; bd[i] += wk * sign * d[i]; }
    }
    const n = Math.max(Math.hypot(br[0], br[1], br[2], br[3]), 1e-12);
    for (let i = 0; i < 4; i++) { br[i] /= n; bd[i] /= n; }
    const [qw, qx, qy, qz] = br;
    const t = qmul(bd, [qw, -qx, -qy, -qz]);
    const x = rest[3 * v], y = rest[3 * v + 1], z = rest[3 * v + 2];
    out[3 * v] = (1 - 2 * (qy * qy + qz * qz)) * x + 2 * (qx * qy - qw * qz) * y + 2 * (qx * qz + qw * qy) * z + 2 * t[1];
    out[3 * v + 1] = 2 * (qx * qy + qw * qz) * x + (1 - 2 * (qx * qx + qz * qz)) * y + 2 * (qy * qz - qw * qx) * z + 2 * t[2];
    out[3 * v + 2] = 2 * (qx * qz - qw * qy) * x + 2 * (qy * qz + qw * qx) * y + (1 - 2 * (qx * qx + qy * qy)) * z + 2 * t[3];
  }
}

export function vertexNormals(verts, faces) {
  const acc = new Float64Array(verts.length);
  for (let f = 0; f < faces.length; f += 3) {
    const a = 3 * faces[f], b = 3 * faces[f + 1], c = 3 * faces[f + 2];
    const e1x = verts[b] - verts[a], e1y = verts[b + 1] - verts[a + 1], e1z = verts[b + 2] - verts[a + 2];
    const e2x = verts[c] - verts[a], e2y = verts[c + 1] - verts[a + 1], e2z = verts[c + 2] - verts[a + 2];
    const nx = e1y * e2z - e1z * e2y, ny = e1z * e2x - e1x * e2z, nz = e1x * e2y - e1y * e2x;
    for (const v of [a, b, c]) { acc[v] += nx; acc[v + 1] += ny; acc[v + 2] += nz; }
  }
  for (let v = 0; v < acc.length; v += 3) {
    const len = Math.hypot(acc[v], acc[v + 1], acc[v + 2]);
    const s = len > ZERO_NORMAL_EPS ? 1 / Math.max(len, ZERO_NORMAL_EPS) : 0;
    acc[v] *= s; acc[v + 1] *= s; acc[v + 2] *= s;
  }
  return acc;
}

// (3, S, S) channel-first normal map of vertex normals through the texel table (0 off the atlas).
export function normalMap(vn, texelVerts, texelWeights, side) {
  const n = side * side, out = new Float32Array(3 * n);
  for (let t = 0; t < n; t++) {
    let x = 0, y = 0, z = 0;
    for (let k = 0; k < 3; k++) {
      const v = 3 * texelVerts[3 * t + k], w = texelWeights[3 * t + k];
      x += w * vn[v]; y += w * vn[v + 1]; z += w * vn[v + 2];
    }
    const sq = x * x + y * y + z * z;
    const s = sq > NORMAL_EPS2 ? 1 / Math.sqrt(sq) : 0;
    out[t] = x * s; out[n + t] = y * s; out[2 * n + t] = z * s;
  }
  return out;
}

// The posed surfaces and normal maps of every frame, computed on first use and kept (a few frames).
export class FrameGeometry {
  constructor(scene, arrays, side, keep = 8) {
    this.scene = scene;
    this.side = side;
    this.a = name => arrays(scene[name]);
    this.motion = scene.motion;
    this.m = name => arrays(scene.motion[name]);
    this.faces = this.a('faces');
    this.offsets = this.a('offsets');
    this.cache = new Map();
    this.keep = keep;
  }

  get numFrames() { return this.motion.frames; }

  pose(frame) {
    const V = this.scene.num_verts, out = new Float64Array(3 * V), mo = this.motion;
    if (mo.kind === 'vertices') {
      out.set(this.m('verts').subarray(frame * 3 * V, (frame + 1) * 3 * V));
      return out;
    }
    if (mo.kind === 'smpl') return (this.smpl ??= new SMPLPoser(mo, this.m)).pose(frame, out);
    const idx = this.m('skin_indices'), K = mo.skin_indices.shape[1], nb = mo.bones.shape[1];
    const args = [this.m('rest_verts'), idx, this.m('skin_weights'), K, this.m('bones'), frame * nb * 12];
    if (mo.skinning === 'lbs') lbs(...args, out); else dqs(...args, nb, out);
    return out;
  }

  // {inner, outer} (V*3 doubles) and their normal maps {nmInner, nmOuter} ((3, S, S) float32) of `frame`.
  get(frame) {
    if (this.cache.has(frame)) return this.cache.get(frame);
    const inner = this.pose(frame), vnIn = vertexNormals(inner, this.faces);
    const outer = new Float64Array(inner.length);
    for (let v = 0; v < this.offsets.length; v++) {
      for (let i = 0; i < 3; i++) outer[3 * v + i] = inner[3 * v + i] + this.offsets[v] * vnIn[3 * v + i];
    }
    const vnOut = vertexNormals(outer, this.faces), tv = this.a('texel_verts'), tw = this.a('texel_weights');
    const g = {inner, outer, nmInner: normalMap(vnIn, tv, tw, this.side), nmOuter: normalMap(vnOut, tv, tw, this.side)};
    this.cache.set(frame, g);
    if (this.cache.size > this.keep) this.cache.delete(this.cache.keys().next().value);
    return g;
  }

  // (3 (T + 1), S, S) temporal window of `surface` ('nmInner' | 'nmOuter'): frames f, f-1, ..., f-T clamped at 0.
  window(frame, T, surface) {
    const n = 3 * this.side * this.side, out = new Float32Array((T + 1) * n);
    for (let k = 0; k <= T; k++) out.set(this.get(Math.max(frame - k, 0))[surface], k * n);
    return out;
  }
}
