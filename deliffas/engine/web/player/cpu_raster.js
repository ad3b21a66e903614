// The two surfaces rasterised on the CPU (the CPU backend), as raster.js does on the GPU: the inner surface's first
// hit, the outer surface's first hit and its exit hit by depth peeling (PEEL_EPS_REL). Every pixel centre in a
// triangle's screen box (grown by a pixel) is tested by ray-triangle intersection with the same tolerance as
// raster.js's fragment shader, and the nearest hit kept (a z-buffer per target). Each target holds
// (u, v, camera depth z, 1) per pixel, 0 where missed, rows top down (image rows).

const T = 1e-4;  // raster.js: a shared edge belongs to both of its triangles

export class CpuRaster {
  constructor(faces, uvs, faceUvs) {
    this.faces = faces;
    const n = faces.length;
    this.cornerUv = new Float64Array(2 * n);  // per face corner: its uv
    for (let c = 0; c < n; c++) {
      const t = faceUvs[c];
      this.cornerUv[2 * c] = uvs[2 * t]; this.cornerUv[2 * c + 1] = uvs[2 * t + 1];
    }
    this.targets = null;
  }

  ensureTargets(w, h) {
    if (this.targets && this.targets.inner.w === w && this.targets.inner.h === h) return this.targets;
    const target = () => ({w, h, data: new Float32Array(w * h * 4)});
    this.targets = {inner: target(), outer: target(), exit: target()};
    this.zbuf = new Float64Array(w * h);
    return this.targets;
  }

  // Camera coordinates of `verts` (V*3 doubles, world mm).
  toCamera(verts, cam) {
    const E = cam.world_to_cam, out = new Float64Array(verts.length);
    for (let v = 0; v < verts.length; v += 3) {
      const x = verts[v], y = verts[v + 1], z = verts[v + 2];
      for (let r = 0; r < 3; r++) out[v + r] = E[r][0] * x + E[r][1] * y + E[r][2] * z + E[r][3];
    }
    return out;
  }

  // The nearest hit of every pixel centre on the triangles of `P` (camera coordinates) into `target`; with `peel`
  // (the first-hit target) only hits beyond peel's depth + eps (raster.js's uPeel).
  draw(target, P, cam, peel = null, eps = 0) {
    const {w: W, h: H, data} = target, zb = this.zbuf, f = this.faces, uv = this.cornerUv, first = peel && peel.data;
    data.fill(0);
    zb.fill(Infinity);
    const K = cam.K, fx = K[0][0], sk = K[0][1], cx = K[0][2], fy = K[1][1], cy = K[1][2];
    const ax = 1 / fx, bx = -sk / (fx * fy), cxx = (sk * cy - cx * fy) / (fx * fy), ay = 1 / fy, cyy = -cy / fy;
    const epsF = Math.fround(eps);
    for (let c = 0; c < f.length; c += 3) {
      const i0 = 3 * f[c], i1 = 3 * f[c + 1], i2 = 3 * f[c + 2];
      const p0x = P[i0], p0y = P[i0 + 1], p0z = P[i0 + 2];
      const e1x = P[i1] - p0x, e1y = P[i1 + 1] - p0y, e1z = P[i1 + 2] - p0z;
      const e2x = P[i2] - p0x, e2y = P[i2 + 1] - p0y, e2z = P[i2 + 2] - p0z;
      // the screen box of the corners, grown by a pixel (the whole image for a corner behind the camera)
      let x0 = 0, x1 = W - 1, y0 = 0, y1 = H - 1;
      if (p0z > 0 && P[i1 + 2] > 0 && P[i2 + 2] > 0) {
        let umin = Infinity, umax = -Infinity, vmin = Infinity, vmax = -Infinity;
        for (const i of [i0, i1, i2]) {
          const X = P[i], Y = P[i + 1], Z = P[i + 2];
          const u = (fx * X + sk * Y + cx * Z) / Z, v = (fy * Y + cy * Z) / Z;
          umin = Math.min(umin, u); umax = Math.max(umax, u); vmin = Math.min(vmin, v); vmax = Math.max(vmax, v);
        }
        x0 = Math.max(0, Math.floor(umin - 1.5)); x1 = Math.min(W - 1, Math.ceil(umax + 0.5));
        y0 = Math.max(0, Math.floor(vmin - 1.5)); y1 = Math.min(H - 1, Math.ceil(vmax + 0.5));
        if (x0 > x1 || y0 > y1) continue;
      }
      // Moeller-Trumbore with d = K^-1 (x, y, 1), s = -P0: each term is linear in d.
      const sx = -p0x, sy = -p0y, sz = -p0z;
      const nx = e2y * e1z - e2z * e1y, ny = e2z * e1x - e2x * e1z, nz = e2x * e1y - e2y * e1x;  // e2 x e1
      const mx = e2y * sz - e2z * sy, my = e2z * sx - e2x * sz, mz = e2x * sy - e2y * sx;        // e2 x s
      const qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;        // s x e1
      const zq = e2x * qx + e2y * qy + e2z * qz;
      const u0 = uv[2 * c], v0 = uv[2 * c + 1], u1 = uv[2 * c + 2], v1 = uv[2 * c + 3];
      const u2 = uv[2 * c + 4], v2 = uv[2 * c + 5];
      for (let y = y0; y <= y1; y++) {
        const dy = ay * (y + 0.5) + cyy, rowX = bx * (y + 0.5) + cxx;
        const denY = ny * dy + nz, b1Y = my * dy + mz, b2Y = qy * dy + qz;
        for (let x = x0; x <= x1; x++) {
          const dx = ax * (x + 0.5) + rowX;
          const inv = 1 / (nx * dx + denY);
          const b1 = (mx * dx + b1Y) * inv, b2 = (qx * dx + b2Y) * inv, z = zq * inv;
          if (!(b1 >= -T && b2 >= -T && b1 + b2 <= 1 + T && z > 0)) continue;
          const p = y * W + x;
          if (z >= zb[p]) continue;
          if (first && first[4 * p + 3] > 0 && z <= first[4 * p + 2] + epsF) continue;
          zb[p] = z;
          const b0 = 1 - b1 - b2, o = 4 * p;
          data[o] = b0 * u0 + b1 * u1 + b2 * u2;
          data[o + 1] = b0 * v0 + b1 * v1 + b2 * v2;
          data[o + 2] = z;
          data[o + 3] = 1;
        }
      }
    }
  }

  // Rasterise `inner` and `outer` (V*3 doubles) for `cam` ({K, world_to_cam, width, height}).
  run(inner, outer, cam) {
    const t = this.ensureTargets(cam.width, cam.height);
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let v = 0; v < outer.length; v += 3) {
      for (let i = 0; i < 3; i++) { lo[i] = Math.min(lo[i], outer[v + i]); hi[i] = Math.max(hi[i], outer[v + i]); }
    }
    const eps = 1e-5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);  // raycast.PEEL_EPS_REL
    const po = this.toCamera(outer, cam);
    this.draw(t.outer, po, cam);
    this.draw(t.exit, po, cam, t.outer, eps);
    this.draw(t.inner, this.toCamera(inner, cam), cam);
    return t;
  }
}
