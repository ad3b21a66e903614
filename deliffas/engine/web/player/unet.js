// The U-Nets as fragment-shader passes: one pass per 4 x 4 stride-2 (transposed) convolution over RGBA32F
// textures, four channels per texel, groups of channels stacked vertically (group g in rows g*H .. g*H+H-1).

import {FULLSCREEN_VS, bindTextures, drawFullscreen, floatTexture, program, renderTarget} from './gl.js';

const CONV_FS = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
uniform sampler2D uA, uB, uW, uPost;
uniform int uGA, uGB, uInH, uInW, uOutH, uTransposed, uAct;
uniform float uSlope;
out vec4 outColor;
vec4 fetchIn(int g, int y, int x) {
  if (g < uGA) return texelFetch(uA, ivec2(x, y + g * uInH), 0);
  return texelFetch(uB, ivec2(x, y + (g - uGA) * uInH), 0);
}
int source(int o, int k) {  // input index of output o at tap k, -1 outside
  int i;
  if (uTransposed == 0) { i = 2 * o - 1 + k; }
  else { int t = o + 1 - k; if (t < 0 || (t & 1) != 0) return -1; i = t >> 1; }
  return i;
}
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  int go = p.y / uOutH, oy = p.y - go * uOutH, ox = p.x;
  int gin = uGA + uGB;
  vec4 acc = vec4(0.0);
  for (int ky = 0; ky < 4; ky++) {
    int iy = source(oy, ky);
    if (iy < 0 || iy >= uInH) continue;
    for (int kx = 0; kx < 4; kx++) {
      int ix = source(ox, kx);
      if (ix < 0 || ix >= uInW) continue;
      int col = (ky * 4 + kx) * 4;
      for (int g = 0; g < gin; g++) {
        int row = go * gin + g;
        mat4 m = mat4(texelFetch(uW, ivec2(col, row), 0), texelFetch(uW, ivec2(col + 1, row), 0),
                      texelFetch(uW, ivec2(col + 2, row), 0), texelFetch(uW, ivec2(col + 3, row), 0));
        acc += m * fetchIn(g, iy, ix);
      }
    }
  }
  acc = acc * texelFetch(uPost, ivec2(go, 0), 0) + texelFetch(uPost, ivec2(go, 1), 0);
  if (uAct == 0) acc = max(acc, 0.0) + uSlope * min(acc, 0.0);
  else if (uAct == 1) acc = max(acc, 0.0);
  else acc = 1.0 / (1.0 + exp(-acc));
  outColor = acc;
}`;

const ACTS = {leaky: 0, relu: 1, sigmoid: 2};

// One U-Net: its layers' weight textures and output targets, built once; run(input) per frame.
export class UNetPasses {
  constructor(gl, desc, side, arrays, vao) {
    this.gl = gl;
    this.vao = vao;
    this.prog = UNetPasses.program(gl);
    this.dummy = floatTexture(gl, 1, 1);
    this.ops = [];
    let size = side;
    for (const op of desc.ops) {
      size = op.kind === 'conv' ? size / 2 : size * 2;
      const w = arrays(op.weights);
      this.ops.push({...op, inSize: op.kind === 'conv' ? size * 2 : size / 2, outSize: size,
                     w: floatTexture(gl, 64, op.out_groups * op.in_groups, w),
                     post: floatTexture(gl, op.out_groups, 2, arrays(op.post)),
                     out: renderTarget(gl, size, size * op.out_groups)});
    }
    this.inGroups = (desc.in_channels + 3) >> 2;
  }

  static program(gl) {
    if (!gl.__deliffasConv) gl.__deliffasConv = program(gl, FULLSCREEN_VS, CONV_FS);
    return gl.__deliffasConv;
  }

  // input: texture of the stacked temporal normal map; returns the feature map's target (groups stacked).
  run(input) {
    const gl = this.gl, prog = this.prog;
    gl.useProgram(prog.p);
    const downs = [];
    let a = input, b = null, ga = this.inGroups, gb = 0;
    for (const op of this.ops) {
      bindTextures(gl, prog, {uA: a, uB: b || this.dummy, uW: op.w, uPost: op.post});
      gl.uniform1i(prog.u.uGA, ga);
      gl.uniform1i(prog.u.uGB, gb);
      gl.uniform1i(prog.u.uInH, op.inSize);
      gl.uniform1i(prog.u.uInW, op.inSize);
      gl.uniform1i(prog.u.uOutH, op.outSize);
      gl.uniform1i(prog.u.uTransposed, op.kind === 'convT' ? 1 : 0);
      gl.uniform1i(prog.u.uAct, ACTS[op.act]);
      gl.uniform1f(prog.u.uSlope, op.slope);
      drawFullscreen(gl, op.out, this.vao);
      if (op.kind === 'conv') {
        downs.push(op);
        a = op.out; b = null; ga = op.out_groups; gb = 0;
      } else if (op.skip !== undefined) {
        const skip = downs[op.skip];
        a = op.out; b = skip.out; ga = op.out_groups; gb = skip.out_groups;
      } else {
        a = op.out;
      }
    }
    return this.ops[this.ops.length - 1].out;
  }
}
