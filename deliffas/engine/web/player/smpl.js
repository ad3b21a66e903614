// SMPL posing on the CPU, in double precision, as deliffas.geometry.smpl.smpl_lbs poses: per frame Rodrigues of
// the 24 axis-angle rotations, the pose feature (R_j - I of joints 1..23) times the pose blend shapes added to the
// shaped rest mesh, the rigid transforms along the kinematic chain, linear blend skinning, then the translation.
// The export (deliffas/engine/web/scene_pack.py) gives the shaped rest mesh and its joints (the betas applied),
// the parents, the skin as K (joint, weight) pairs per vertex, and the pose blend shapes' non-zero rows only
// (`pose_rows`), as float32 or as the bytes of float16.

// float16 bits -> float32 (exact: every float16 is a float32).
function halfToFloat(bits) {
  const out = new Float32Array(bits.length);
  for (let i = 0; i < bits.length; i++) {
    const h = bits[i], s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    out[i] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1024 + m) * 2 ** (e - 25);
  }
  return out;
}

// (3, 3) row-major rotation of an axis-angle vector, as batch_rodrigues (its angle of r + 1e-8, as smplx).
export function rodrigues(rx, ry, rz) {
  const angle = Math.hypot(rx + 1e-8, ry + 1e-8, rz + 1e-8);
  const x = rx / angle, y = ry / angle, z = rz / angle, s = Math.sin(angle), c = 1 - Math.cos(angle);
  const K = [0, -z, y, z, 0, -x, -y, x, 0], R = new Float64Array(9);
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 3; j++) {
      let kk = 0;
      for (let l = 0; l < 3; l++) kk += K[3 * i + l] * K[3 * l + j];
      R[3 * i + j] = (i === j ? 1 : 0) + s * K[3 * i + j] + c * kk;
    }
  }
  return R;
}

export class SMPLPoser {
  // motion: the scene's motion entry (kind 'smpl'); m: name -> the typed array of one of its entries.
  constructor(motion, m) {
    this.motion = motion;
    this.vShaped = m('v_shaped');
    this.joints = m('joints');
    this.parents = motion.parents;
    this.skinIdx = m('skin_indices');
    this.skinW = m('skin_weights');
    this.K = motion.skin_indices.shape[1];
    this.rows = motion.pose_rows;
    const pd = m('posedirs');
    this.posedirs = motion.posedirs_dtype === 'float16'
      ? halfToFloat(new Uint16Array(pd.buffer, pd.byteOffset, pd.length / 2)) : pd;
    this.poses = m('poses');
    this.transl = m('transl');
  }

  // The posed vertices (V*3 doubles, mm) of `frame` into `out`.
  pose(frame, out) {
    const J = this.parents.length, V = this.vShaped.length / 3, V3 = 3 * V;
    const pose = this.poses.subarray(frame * 3 * J, (frame + 1) * 3 * J);
    const rot = [];
    for (let j = 0; j < J; j++) rot.push(rodrigues(pose[3 * j], pose[3 * j + 1], pose[3 * j + 2]));
    // v_posed = v_shaped + pose_feature @ posedirs (the feature's rows the export kept)
    const vPosed = Float64Array.from(this.vShaped);
    this.rows.forEach((row, r) => {
      const j = 1 + Math.floor(row / 9), e = row % 9;
      const f = rot[j][e] - (e % 4 === 0 ? 1 : 0);
      if (f === 0) return;
      const o = r * V3;
      for (let i = 0; i < V3; i++) vPosed[i] += f * this.posedirs[o + i];
    });
    // global 3 x 4 transforms along the chain, then relative to the rest joints
    const glob = [], T = new Float64Array(12 * J), jt = this.joints;
    for (let j = 0; j < J; j++) {
      const p = this.parents[j], R = rot[j], G = new Float64Array(12);
      const rel = [0, 1, 2].map(i => jt[3 * j + i] - (p >= 0 ? jt[3 * p + i] : 0));
      if (p < 0) {
        for (let i = 0; i < 3; i++) {
          for (let k = 0; k < 3; k++) G[4 * i + k] = R[3 * i + k];
          G[4 * i + 3] = rel[i];
        }
      } else {
        const P = glob[p];
        for (let i = 0; i < 3; i++) {
          for (let k = 0; k < 3; k++) {
            G[4 * i + k] = P[4 * i] * R[k] + P[4 * i + 1] * R[3 + k] + P[4 * i + 2] * R[6 + k];
          }
          G[4 * i + 3] = P[4 * i] * rel[0] + P[4 * i + 1] * rel[1] + P[4 * i + 2] * rel[2] + P[4 * i + 3];
        }
      }
      glob.push(G);
      for (let i = 0; i < 3; i++) {
        for (let k = 0; k < 3; k++) T[12 * j + 4 * i + k] = G[4 * i + k];
        T[12 * j + 4 * i + 3] = G[4 * i + 3]
          - (G[4 * i] * jt[3 * j] + G[4 * i + 1] * jt[3 * j + 1] + G[4 * i + 2] * jt[3 * j + 2]);
      }
    }
    // linear blend skinning, then the translation
    const K = this.K, idx = this.skinIdx, w = this.skinW, M = new Float64Array(12);
    const tx = this.transl[3 * frame], ty = this.transl[3 * frame + 1], tz = this.transl[3 * frame + 2];
    for (let v = 0; v < V; v++) {
      M.fill(0);
      for (let k = 0; k < K; k++) {
        const wk = w[v * K + k];
        if (wk === 0) continue;
        const o = 12 * idx[v * K + k];
        for (let i = 0; i < 12; i++) M[i] += wk * T[o + i];
      }
      const x = vPosed[3 * v], y = vPosed[3 * v + 1], z = vPosed[3 * v + 2];
      out[3 * v] = M[0] * x + M[1] * y + M[2] * z + M[3] + tx;
      out[3 * v + 1] = M[4] * x + M[5] * y + M[6] * z + M[7] + ty;
      out[3 * v + 2] = M[8] * x + M[9] * y + M[10] * z + M[11] + tz;
    }
    return out;
  }
}
