// The light field per pixel, one fragment-shader pass: the rays' uvs from the raster targets (depth peeling where
// the inner surface is missed), the feature maps sampled bilinearly at those uvs, the positional encodings of the
// uvs and of the (reflected) view direction, and the MLP, whose weights are rows of a float texture.

import {FULLSCREEN_VS, bindTextures, drawFullscreen, program, unetSide} from './gl.js';

const ceil4 = n => (n + 3) >> 2 << 2;

// Bilinear lookups into stacked maps of side `side` (grid_sample, align_corners=False, border) and one surface's
// features: the feature maps at the U-Nets' side SF, the texture atlas at the atlas side S.
const SAMPLING_GLSL = `
vec4 bilinear(sampler2D t, int side, int group, vec2 uv) {
  float fs = float(side);
  float x = clamp(uv.x * fs - 0.5, 0.0, fs - 1.0), y = clamp((1.0 - uv.y) * fs - 0.5, 0.0, fs - 1.0);
  int x0 = int(floor(x)), y0 = int(floor(y)), x1 = min(x0 + 1, side - 1), y1 = min(y0 + 1, side - 1);
  float ax = x - float(x0), ay = y - float(y0);
  int o = group * side;
  vec4 a = mix(texelFetch(t, ivec2(x0, y0 + o), 0), texelFetch(t, ivec2(x1, y0 + o), 0), ax);
  vec4 b = mix(texelFetch(t, ivec2(x0, y1 + o), 0), texelFetch(t, ivec2(x1, y1 + o), 0), ax);
  return mix(a, b, ay);
}
void addMap(inout float f[MAXIN], int k, sampler2D maps, sampler2D tex, vec2 uv) {
  for (int g = 0; g < (C + 3) / 4; g++) {
    vec4 v = bilinear(maps, SF, g, uv);
    for (int j = 0; j < 4; j++) if (4 * g + j < C) f[k + 4 * g + j] = v[j];
  }
  for (int g = 0; g < (CT + 3) / 4; g++) {
    vec4 v = bilinear(tex, S, g, uv);
    for (int j = 0; j < 4; j++) if (4 * g + j < CT) f[k + C + 4 * g + j] = v[j];
  }
}
vec4 group4(float a[MAXIN], int g) { return vec4(a[4 * g], a[4 * g + 1], a[4 * g + 2], a[4 * g + 3]); }
`;

// The MLP, four outputs at a time: x * mat4(four weight rows) is their four dot products; the features enter in
// front of the layer after feature_layer.
const MLP_GLSL = `
vec3 lightField(float x[MAXIN], float f[MAXIN]) {
  vec4 xv[MAXG], yv[MAXG];
  for (int g = 0; g < MAXG; g++) xv[g] = group4(x, g);
  for (int l = 0; l < NL; l++) {
    int front = l + 1 < NL ? L_FRONT[l + 1] / 4 : 0, groups = L_IN[l] / 4;
    for (int g = 0; g < front; g++) yv[g] = group4(f, g);
    for (int og = 0; og < (L_OUT[l] + 3) / 4; og++) {
      int row = L_ROW[l] + 4 * og;
      vec4 acc = vec4(texelFetch(uMlp, ivec2(groups, row), 0).x, texelFetch(uMlp, ivec2(groups, row + 1), 0).x,
                      texelFetch(uMlp, ivec2(groups, row + 2), 0).x, texelFetch(uMlp, ivec2(groups, row + 3), 0).x);
      for (int g = 0; g < groups; g++) {
        acc += xv[g] * mat4(texelFetch(uMlp, ivec2(g, row), 0), texelFetch(uMlp, ivec2(g, row + 1), 0),
                            texelFetch(uMlp, ivec2(g, row + 2), 0), texelFetch(uMlp, ivec2(g, row + 3), 0));
      }
      yv[front + og] = l + 1 < NL ? max(acc, 0.0) : acc;
    }
    for (int g = 0; g < MAXG; g++) xv[g] = yv[g];
  }
  return 1.0 / (1.0 + exp(-xv[0].xyz));
}
`;

// GLSL appending the positional encoding [v, sin(f_0 v), cos(f_0 v), sin(f_1 v), ...] of `name` to x at k.
function encoding(name, dim, L, freqs) {
  return `for (int d = 0; d < ${dim}; d++) x[k++] = ${name}[d];
  for (int l = 0; l < ${L}; l++) {
    for (int d = 0; d < ${dim}; d++) x[k + d] = sin(${name}[d] * ${freqs}[l]);
    for (int d = 0; d < ${dim}; d++) x[k + ${dim} + d] = cos(${name}[d] * ${freqs}[l]);
    k += ${2 * dim};
  }`;
}

function header(model) {
  const mlp = model.mlp, ints = key => `int[](${mlp.layers.map(l => l[key]).join(', ')})`;
  const maxIn = Math.max(...mlp.layers.map(l => l.in), ceil4(mlp.width) + ceil4(mlp.feature_dim));
  return `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
uniform sampler2D uInnerHit, uOuterHit, uExitHit, uInnerF, uOuterF, uInnerT, uOuterT, uNormal, uMlp;
uniform mat3 uRay; uniform float uHeight; uniform float uFreq[16]; uniform float uFreqDir[16];
out vec4 outColor;
const int S = ${model.atlas_res}, SF = ${unetSide(model)}, C = ${model.feature_channels};
const int CT = ${model.texture_channels};
const int NL = ${mlp.layers.length}, MAXIN = ${maxIn}, MAXG = ${maxIn / 4};
const int L_IN[NL] = ${ints('in')}; const int L_OUT[NL] = ${ints('out')};
const int L_ROW[NL] = ${ints('row')}; const int L_FRONT[NL] = ${ints('front')};`;
}

function shaderSource(model) {
  const s = model.spec, width = model.feature_channels + model.texture_channels;
  const encoded = s.encoded_uvs.map(w => encoding(w === 'outer' ? 'uvOut' : 'uvIn', 2, model.pe_freqs, 'uFreq'));
  if (s.viewdir) encoded.push(encoding('dir', 3, model.viewdir_pe_freqs, 'uFreqDir'));
  const reflect = `vec3 n = bilinear(uNormal, S, 0, uvIn).xyz; n = n / max(length(n), 1e-6);
  dir = dir - 2.0 * dot(dir, n) * n;`;
  return `${header(model)}
${SAMPLING_GLSL}
${MLP_GLSL}
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec4 hitIn = texelFetch(uInnerHit, p, 0), hitOut = texelFetch(uOuterHit, p, 0), hitExit = texelFetch(uExitHit, p, 0);
  if (hitOut.w == 0.0 || (hitIn.w == 0.0 && hitExit.w == 0.0)) { outColor = vec4(0.0, 0.0, 0.0, 1.0); return; }
  bool peeled = hitIn.w == 0.0;
  vec2 uvOut = hitOut.xy, uvIn = peeled ? hitExit.xy : hitIn.xy;
  vec3 dir = normalize(uRay * vec3(gl_FragCoord.x, uHeight - gl_FragCoord.y, 1.0));
  ${s.reflect_viewdir ? reflect : ''}
  float f[MAXIN], x[MAXIN];
  for (int i = 0; i < MAXIN; i++) { f[i] = 0.0; x[i] = 0.0; }
  int k = 0;
  ${s.outer_unet ? `addMap(f, k, uOuterF, uOuterT, uvOut); k += ${width};` : ''}
  ${s.inner_from_outer ? 'if (peeled) addMap(f, k, uOuterF, uOuterT, uvIn); else ' : ''}addMap(f, k, uInnerF, uInnerT, uvIn);
  k = 0;
  ${encoded.join('\n  ')}
  outColor = vec4(lightField(x, f), 1.0);
}`;
}

export class LightFieldPass {
  constructor(gl, model, mlpTexture, vao) {
    this.gl = gl;
    this.model = model;
    this.vao = vao;
    this.mlp = mlpTexture;
    this.prog = program(gl, FULLSCREEN_VS, shaderSource(model));
    const freqs = L => Array.from({length: 16}, (_, k) => (k < L ? Math.fround(Math.PI * 2 ** k) : 0));
    gl.useProgram(this.prog.p);
    gl.uniform1fv(this.prog.u.uFreq, freqs(model.pe_freqs));
    gl.uniform1fv(this.prog.u.uFreqDir, freqs(model.viewdir_pe_freqs));
  }

  // Shade `cam` into the canvas: hits from SurfaceRaster.run, maps {innerF, outerF, innerT, outerT, normal}.
  run(hits, maps, cam) {
    const gl = this.gl, u = this.prog.u;
    gl.useProgram(this.prog.p);
    bindTextures(gl, this.prog, {uInnerHit: hits.inner, uOuterHit: hits.outer, uExitHit: hits.exit,
                                 uInnerF: maps.innerF, uOuterF: maps.outerF, uInnerT: maps.innerT,
                                 uOuterT: maps.outerT, uNormal: maps.normal, uMlp: this.mlp});
    gl.uniformMatrix3fv(u.uRay, false, rayMatrix(cam));
    gl.uniform1f(u.uHeight, cam.height);
    drawFullscreen(gl, null, this.vao);
  }
}

// R^T K^-1, column-major: the world direction of image point (x, y, 1).
export function rayMatrix(cam) {
  const K = cam.K, E = cam.world_to_cam;
  const fx = K[0][0], s = K[0][1], cx = K[0][2], fy = K[1][1], cy = K[1][2];
  const Ki = [[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], [0, 1 / fy, -cy / fy], [0, 0, 1]];
  const M = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) for (let k = 0; k < 3; k++) M[i][j] += E[k][i] * Ki[k][j];
  return [M[0][0], M[1][0], M[2][0], M[0][1], M[1][1], M[2][1], M[0][2], M[1][2], M[2][2]];
}
