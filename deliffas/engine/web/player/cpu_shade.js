// The light field per pixel on the CPU (the CPU backend), as shade.js's fragment shader computes it: the rays' uvs
// from the raster targets (depth peeling where the inner surface is missed), the feature maps sampled bilinearly
// (grid_sample, align_corners=False, border), the positional encodings of the uvs and of the (reflected) view
// direction, and the MLP from the same table of weight rows. Writes RGBA bytes, rows top down.

import {unetSide} from './gl.js';
import {rayMatrix} from './shade.js';

const ceil4 = n => (n + 3) >> 2 << 2;

// out[k + j] = the bilinear sample of channel j < count of group `group` of stacked maps `t` (side S) at uv.
function bilinear(t, S, group, u, v, out, k, count) {
  const x = Math.min(Math.max(u * S - 0.5, 0), S - 1), y = Math.min(Math.max((1 - v) * S - 0.5, 0), S - 1);
  const x0 = Math.floor(x), y0 = Math.floor(y), x1 = Math.min(x0 + 1, S - 1), y1 = Math.min(y0 + 1, S - 1);
  const ax = x - x0, ay = y - y0, o = group * S;
  const p00 = ((y0 + o) * S + x0) * 4, p01 = ((y0 + o) * S + x1) * 4;
  const p10 = ((y1 + o) * S + x0) * 4, p11 = ((y1 + o) * S + x1) * 4;
  for (let j = 0; j < count; j++) {
    const a = t[p00 + j] + (t[p01 + j] - t[p00 + j]) * ax, b = t[p10 + j] + (t[p11 + j] - t[p10 + j]) * ax;
    out[k + j] = a + (b - a) * ay;
  }
}

// One surface's features at uv into f from k: the feature maps' C channels (side SF, the U-Nets'), then the texture
// atlas's CT (side S, the atlas's).
function addMap(f, k, SF, maps, C, S, tex, CT, u, v) {
  for (let g = 0; g < (C + 3) >> 2; g++) bilinear(maps, SF, g, u, v, f, k + 4 * g, Math.min(4, C - 4 * g));
  for (let g = 0; g < (CT + 3) >> 2; g++) bilinear(tex, S, g, u, v, f, k + C + 4 * g, Math.min(4, CT - 4 * g));
}

// The positional encoding [v, sin(f_0 v), cos(f_0 v), sin(f_1 v), ...] of vals[0..dim) into x at k; returns k.
function encode(x, k, vals, dim, freqs) {
  for (let d = 0; d < dim; d++) x[k++] = vals[d];
  for (const fr of freqs) {
    for (let d = 0; d < dim; d++) {
      const a = Math.fround(vals[d] * fr);  // the shader's float product
      x[k + d] = Math.sin(a);
      x[k + dim + d] = Math.cos(a);
    }
    k += 2 * dim;
  }
  return k;
}

// One MLP layer on a batch of n (a multiple of 4) rows of x (row stride ms): y's rows = [f's first `front`
// values, act(W x + b)], four rows times four outputs at a time (W: the table's rows from `row`, bias at `nin`).
function layer(W, stride, row, nin, outs, x, y, ms, f, nf, front, n, relu) {
  for (let r = 0; r < n; r++) for (let i = 0; i < front; i++) y[r * ms + i] = f[r * nf + i];
  for (let r = 0; r < n; r += 4) {
    const x0 = r * ms, x1 = x0 + ms, x2 = x1 + ms, x3 = x2 + ms;
    for (let o = 0; o < outs; o += 4) {
      const w0 = (row + o) * stride, w1 = w0 + stride, w2 = w1 + stride, w3 = w2 + stride;
      let a00 = W[w0 + nin], a01 = W[w1 + nin], a02 = W[w2 + nin], a03 = W[w3 + nin];
      let a10 = a00, a11 = a01, a12 = a02, a13 = a03, a20 = a00, a21 = a01, a22 = a02, a23 = a03;
      let a30 = a00, a31 = a01, a32 = a02, a33 = a03;
      for (let i = 0; i < nin; i++) {
        const v0 = W[w0 + i], v1 = W[w1 + i], v2 = W[w2 + i], v3 = W[w3 + i];
        const p = x[x0 + i], q = x[x1 + i], s = x[x2 + i], t = x[x3 + i];
        a00 += v0 * p; a01 += v1 * p; a02 += v2 * p; a03 += v3 * p;
        a10 += v0 * q; a11 += v1 * q; a12 += v2 * q; a13 += v3 * q;
        a20 += v0 * s; a21 += v1 * s; a22 += v2 * s; a23 += v3 * s;
        a30 += v0 * t; a31 += v1 * t; a32 += v2 * t; a33 += v3 * t;
      }
      const acc = [a00, a01, a02, a03, a10, a11, a12, a13, a20, a21, a22, a23, a30, a31, a32, a33];
      for (let j = 0; j < 4; j++) {
        const yb = x0 + j * ms + front + o;
        for (let c = 0; c < 4; c++) {
          const v = acc[4 * j + c];
          y[yb + c] = relu && v < 0 ? 0 : v;
        }
      }
    }
  }
}

const BATCH = 256;  // pixels per MLP batch

export class CpuLightField {
  constructor(model, table) {
    this.model = model;
    this.table = table;
    const mlp = model.mlp;
    this.stride = mlp.table.shape[1];
    this.layers = mlp.layers;
    this.maxIn = Math.max(...mlp.layers.map(l => l.in), ceil4(mlp.width) + ceil4(mlp.feature_dim));
    this.nf = Math.max(ceil4(mlp.feature_dim), 4);
    const freqs = L => Array.from({length: L}, (_, k) => Math.fround(Math.PI * 2 ** k));
    this.freq = freqs(model.pe_freqs);
    this.freqDir = freqs(model.viewdir_pe_freqs);
    this.x = new Float32Array(BATCH * this.maxIn);
    this.y = new Float32Array(BATCH * this.maxIn);
    this.f = new Float32Array(BATCH * this.nf);
    this.pixels = new Int32Array(BATCH);
  }

  // The MLP on the first `count` rows of the batch (encodings this.x, features this.f): their colours into rgba.
  flush(count, rgba) {
    const ms = this.maxIn, nf = this.nf, n = ceil4(count), layers = this.layers, NL = layers.length;
    this.x.fill(0, count * ms, n * ms);
    this.f.fill(0, count * nf, n * nf);
    let x = this.x, y = this.y;
    for (let l = 0; l < NL; l++) {
      const {in: nin, out, row} = layers[l], last = l + 1 === NL, front = last ? 0 : layers[l + 1].front;
      layer(this.table, this.stride, row, nin, ceil4(out), x, y, ms, this.f, nf, front, n, !last);
      [x, y] = [y, x];
    }
    for (let r = 0; r < count; r++) {
      const o = 4 * this.pixels[r];
      for (let c = 0; c < 3; c++) rgba[o + c] = 255 / (1 + Math.exp(-x[r * ms + c]));
    }
  }

  // Shade `cam` into `rgba` (Uint8ClampedArray, W*H*4): hits from CpuRaster.run, maps {innerF, outerF, innerT,
  // outerT, normal} (stacked Float32Arrays; the texture atlases null without them).
  run(hits, maps, cam, rgba) {
    const model = this.model, s = model.spec, S = model.atlas_res, SF = unetSide(model), C = model.feature_channels;
    const CT = model.texture_channels, width = C + CT, W = cam.width, H = cam.height;
    const hIn = hits.inner.data, hOut = hits.outer.data, hExit = hits.exit.data, M = rayMatrix(cam);
    const X = this.x, F = this.f, ms = this.maxIn, nf = this.nf, n = new Float64Array(4);
    const uvIn = [0, 0], uvOut = [0, 0], dir = [0, 0, 0];
    const texIn = maps.innerT || new Float32Array(4), texOut = maps.outerT || new Float32Array(4);
    let count = 0;
    for (let py = 0; py < H; py++) {
      for (let px = 0; px < W; px++) {
        const p = py * W + px, o = 4 * p;
        rgba[o + 3] = 255;
        if (hOut[o + 3] === 0 || (hIn[o + 3] === 0 && hExit[o + 3] === 0)) {
          rgba[o] = rgba[o + 1] = rgba[o + 2] = 0;
          continue;
        }
        const peeled = hIn[o + 3] === 0, hi = peeled ? hExit : hIn;
        uvOut[0] = hOut[o]; uvOut[1] = hOut[o + 1]; uvIn[0] = hi[o]; uvIn[1] = hi[o + 1];
        const a = px + 0.5, b = py + 0.5;
        let dx = M[0] * a + M[3] * b + M[6], dy = M[1] * a + M[4] * b + M[7], dz = M[2] * a + M[5] * b + M[8];
        const len = Math.hypot(dx, dy, dz);
        dx /= len; dy /= len; dz /= len;
        if (s.reflect_viewdir) {
          bilinear(maps.normal, S, 0, uvIn[0], uvIn[1], n, 0, 3);
          const nl = Math.max(Math.hypot(n[0], n[1], n[2]), 1e-6), nx = n[0] / nl, ny = n[1] / nl, nz = n[2] / nl;
          const d2 = 2 * (dx * nx + dy * ny + dz * nz);
          dx -= d2 * nx; dy -= d2 * ny; dz -= d2 * nz;
        }
        dir[0] = dx; dir[1] = dy; dir[2] = dz;
        const fb = count * nf;
        F.fill(0, fb, fb + nf);
        let k = fb;
        if (s.outer_unet) { addMap(F, k, SF, maps.outerF, C, S, texOut, CT, uvOut[0], uvOut[1]); k += width; }
        if (s.inner_from_outer && peeled) addMap(F, k, SF, maps.outerF, C, S, texOut, CT, uvIn[0], uvIn[1]);
        else addMap(F, k, SF, maps.innerF, C, S, texIn, CT, uvIn[0], uvIn[1]);
        const xb = count * ms;
        X.fill(0, xb, xb + ms);
        k = xb;
        for (const w of s.encoded_uvs) k = encode(X, k, w === 'outer' ? uvOut : uvIn, 2, this.freq);
        if (s.viewdir) encode(X, k, dir, 3, this.freqDir);
        this.pixels[count++] = p;
        if (count === BATCH) { this.flush(count, rgba); count = 0; }
      }
    }
    if (count) this.flush(count, rgba);
  }
}
