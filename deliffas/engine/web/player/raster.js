// The two surfaces rasterised for one camera: the inner surface's first hit, the outer surface's first hit and
// its exit (second) hit by depth peeling. Each target holds (u, v, camera depth z, 1) per pixel, 0 where missed.
// Vertices go to the GPU in camera coordinates (computed in double precision here) and are projected by K.

import {renderTarget, deleteTarget, program} from './gl.js';

const RASTER_VS = `#version 300 es
precision highp float;
in vec3 aP0, aP1, aP2; in vec2 aT0, aT1, aT2;
uniform mat3 uK; uniform vec2 uSize; uniform vec2 uRange;
flat out vec3 vP0, vP1, vP2; flat out vec2 vT0, vT1, vT2;
vec2 screen(vec3 pos) { vec3 p = uK * pos; return p.xy / p.z; }
vec2 outward(vec2 a, vec2 b, float side) { vec2 d = normalize(b - a); return side * vec2(d.y, -d.x); }
// Conservative rasterisation: every edge moved out by 1/8 pixel (more than the rasteriser's sub-pixel snapping),
// so every pixel centre inside the triangle gets a fragment; the fragment shader keeps the exact ones.
void main() {
  int k = gl_VertexID % 3;
  vec3 pos = k == 0 ? aP0 : (k == 1 ? aP1 : aP2);
  vec2 s = screen(pos);
  if (aP0.z > uRange.x && aP1.z > uRange.x && aP2.z > uRange.x) {
    vec2 q[3] = vec2[3](screen(aP0), screen(aP1), screen(aP2));
    vec2 e1 = q[1] - q[0], e2 = q[2] - q[0];
    float area = e1.x * e2.y - e1.y * e2.x;
    if (area != 0.0) {
      float side = sign(area);
      vec2 n0 = outward(q[(k + 2) % 3], s, side), n1 = outward(s, q[(k + 1) % 3], side);
      vec2 miter = (n0 + n1) / max(1.0 + dot(n0, n1), 1e-6);  // moves both edges by 1
      float len = length(miter);
      s += 0.125 * miter * min(1.0, 128.0 / max(len, 1e-6));     // at most 16 pixels
    }
  }
  float z = pos.z, n = uRange.x, f = uRange.y;
  gl_Position = vec4((2.0 * s.x / uSize.x - 1.0) * z, (1.0 - 2.0 * s.y / uSize.y) * z,
                     (z * (f + n) - 2.0 * f * n) / (f - n), z);
  vP0 = aP0; vP1 = aP1; vP2 = aP2; vT0 = aT0; vT1 = aT1; vT2 = aT2;
}`;

// The hit is recomputed at the pixel centre by ray-triangle intersection (as the ray caster and the C rasteriser
// find it) rather than read from the rasteriser's interpolation, whose vertices are snapped to its sub-pixel grid.
const RASTER_FS = `#version 300 es
precision highp float; precision highp sampler2D;
flat in vec3 vP0, vP1, vP2; flat in vec2 vT0, vT1, vT2;
uniform int uPeel; uniform float uEps; uniform sampler2D uFirst; uniform mat3 uKinv; uniform float uHeight;
uniform vec2 uRange;
out vec4 outColor;
void main() {
  vec3 d = uKinv * vec3(gl_FragCoord.x, uHeight - gl_FragCoord.y, 1.0);
  vec3 e1 = vP1 - vP0, e2 = vP2 - vP0, h = cross(d, e2), s = -vP0, q = cross(s, e1);
  float inv = 1.0 / dot(e1, h);
  float b1 = dot(s, h) * inv, b2 = dot(d, q) * inv, z = dot(e2, q) * inv * d.z;
  const float T = 1e-4;  // a shared edge belongs to both of its triangles (no cracks from round-off)
  if (b1 < -T || b2 < -T || b1 + b2 > 1.0 + T || z <= 0.0) discard;
  float n = uRange.x, f = uRange.y;
  gl_FragDepth = 0.5 + 0.5 * ((f + n) / (f - n) - 2.0 * f * n / ((f - n) * z));
  if (uPeel == 1) {
    vec4 first = texelFetch(uFirst, ivec2(gl_FragCoord.xy), 0);
    if (first.w > 0.0 && z <= first.z + uEps) discard;
  }
  outColor = vec4((1.0 - b1 - b2) * vT0 + b1 * vT1 + b2 * vT2, z, 1.0);
}`;

export class SurfaceRaster {
  constructor(gl, faces, uvs, faceUvs) {
    this.gl = gl;
    this.prog = program(gl, RASTER_VS, RASTER_FS);
    this.faces = faces;
    const n = faces.length;
    const cornerUv = new Float32Array(6 * n);  // per corner: the three corner uvs of its face
    for (let c = 0; c < n; c++) {
      const f0 = c - (c % 3);
      for (let k = 0; k < 3; k++) {
        const t = faceUvs[f0 + k];
        cornerUv[6 * c + 2 * k] = uvs[2 * t]; cornerUv[6 * c + 2 * k + 1] = uvs[2 * t + 1];
      }
    }
    this.positions = new Float32Array(9 * n);  // per corner: the three corner positions of its face
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const loc = name => gl.getAttribLocation(this.prog.p, name);
    this.posBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posBuf);
    gl.bufferData(gl.ARRAY_BUFFER, this.positions.byteLength, gl.DYNAMIC_DRAW);
    ['aP0', 'aP1', 'aP2'].forEach((name, k) => {
      gl.enableVertexAttribArray(loc(name));
      gl.vertexAttribPointer(loc(name), 3, gl.FLOAT, false, 36, 12 * k);
    });
    const uvBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, uvBuf);
    gl.bufferData(gl.ARRAY_BUFFER, cornerUv, gl.STATIC_DRAW);
    ['aT0', 'aT1', 'aT2'].forEach((name, k) => {
      gl.enableVertexAttribArray(loc(name));
      gl.vertexAttribPointer(loc(name), 2, gl.FLOAT, false, 24, 8 * k);
    });
    gl.bindVertexArray(null);
    this.targets = null;
  }

  ensureTargets(w, h) {
    const gl = this.gl;
    if (this.targets && this.targets.inner.w === w && this.targets.inner.h === h) return this.targets;
    if (this.targets) Object.values(this.targets).forEach(t => deleteTarget(gl, t));
    this.targets = {inner: renderTarget(gl, w, h, true), outer: renderTarget(gl, w, h, true),
                    exit: renderTarget(gl, w, h, true)};
    return this.targets;
  }

  // Camera coordinates of every face corner of `verts` (V*3 doubles, world mm); returns the depth range.
  upload(verts, cam) {
    const E = cam.world_to_cam, f = this.faces, pos = this.positions;
    let zmin = Infinity, zmax = -Infinity;
    const cache = new Float64Array(verts.length);
    for (let v = 0; v < verts.length; v += 3) {
      const x = verts[v], y = verts[v + 1], z = verts[v + 2];
      for (let r = 0; r < 3; r++) cache[v + r] = E[r][0] * x + E[r][1] * y + E[r][2] * z + E[r][3];
      zmin = Math.min(zmin, cache[v + 2]); zmax = Math.max(zmax, cache[v + 2]);
    }
    for (let c = 0; c < f.length; c++) {
      const f0 = c - (c % 3);
      for (let k = 0; k < 3; k++) {
        const v = 3 * f[f0 + k], o = 9 * c + 3 * k;
        pos[o] = cache[v]; pos[o + 1] = cache[v + 1]; pos[o + 2] = cache[v + 2];
      }
    }
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, pos);
    return [zmin, zmax];
  }

  draw(target, cam, range, peel = null, eps = 0) {
    const gl = this.gl, u = this.prog.u;
    gl.bindFramebuffer(gl.FRAMEBUFFER, target.fb);
    gl.viewport(0, 0, target.w, target.h);
    gl.clearColor(0, 0, 0, 0);
    gl.clearDepth(1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.CULL_FACE);
    gl.useProgram(this.prog.p);
    const K = cam.K;
    gl.uniformMatrix3fv(u.uK, false, [K[0][0], K[1][0], K[2][0], K[0][1], K[1][1], K[2][1], K[0][2], K[1][2], K[2][2]]);
    gl.uniform2f(u.uSize, cam.width, cam.height);
    gl.uniform1f(u.uHeight, cam.height);
    const fx = K[0][0], sk = K[0][1], cx = K[0][2], fy = K[1][1], cy = K[1][2];
    gl.uniformMatrix3fv(u.uKinv, false, [1 / fx, 0, 0, -sk / (fx * fy), 1 / fy, 0,
                                         (sk * cy - cx * fy) / (fx * fy), -cy / fy, 1]);
    gl.uniform2f(u.uRange, range[0], range[1]);
    gl.uniform1i(u.uPeel, peel ? 1 : 0);
    gl.uniform1f(u.uEps, eps);
    if (peel) {
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, peel.tex);
      gl.uniform1i(u.uFirst, 0);
    }
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, this.faces.length);
    gl.bindVertexArray(null);
    gl.disable(gl.DEPTH_TEST);
  }

  // Rasterise `inner` and `outer` (V*3 doubles) for `cam` ({K, world_to_cam, width, height}).
  run(inner, outer, cam) {
    const t = this.ensureTargets(cam.width, cam.height);
    const rIn = this.upload(inner, cam);
    const zo = this.upload(outer, cam);
    const near = Math.max(Math.min(rIn[0], zo[0]) * 0.5, 1e-3), far = Math.max(rIn[1], zo[1]) * 2 + 1;
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let v = 0; v < outer.length; v += 3) {
      for (let i = 0; i < 3; i++) { lo[i] = Math.min(lo[i], outer[v + i]); hi[i] = Math.max(hi[i], outer[v + i]); }
    }
    const eps = 1e-5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);  // raycast.PEEL_EPS_REL
    this.draw(t.outer, cam, [near, far]);
    this.draw(t.exit, cam, [near, far], t.outer, eps);
    this.upload(inner, cam);
    this.draw(t.inner, cam, [near, far]);
    return t;
  }
}
