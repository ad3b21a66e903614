// The U-Nets on the CPU (the CPU backend): the layer list and weights unet.js consumes, each 4 x 4 stride-2
// (transposed) convolution computed over Float32Arrays laid out as unet.js's textures: groups of four channels
// stacked vertically, texel (x, y) of group g at ((g * H + y) * W + x) * 4.

const ACTS = {leaky: 0, relu: 1, sigmoid: 2};

// For each output index o: the (tap k, input index i) pairs that reach it (as unet.js's source()).
function tapTable(outSize, inSize, transposed) {
  const table = [];
  for (let o = 0; o < outSize; o++) {
    const taps = [];
    for (let k = 0; k < 4; k++) {
      let i;
      if (!transposed) i = 2 * o - 1 + k;
      else {
        const t = o + 1 - k;
        if (t < 0 || (t & 1) !== 0) continue;
        i = t >> 1;
      }
      if (i >= 0 && i < inSize) taps.push(k, i);
    }
    table.push(Int32Array.from(taps));
  }
  return table;
}

// One layer: out = act((sum over taps and input groups of W x in) * scale + shift); inputs a (ga groups) then b
// (gb groups, the skip concatenation), all of side op.inSize.
function convLayer(op, a, ga, b, gb, out) {
  const H = op.inSize, OH = op.outSize, G = op.out_groups, gin = ga + gb;
  const w = op.w, post = op.post, act = ACTS[op.act], slope = op.slope;
  const taps = op.taps, acc = new Float64Array(4);
  for (let go = 0; go < G; go++) {
    for (let oy = 0; oy < OH; oy++) {
      const ty = taps[oy];
      for (let ox = 0; ox < OH; ox++) {
        const tx = taps[ox];
        let s0 = 0, s1 = 0, s2 = 0, s3 = 0;
        for (let p = 0; p < ty.length; p += 2) {
          const ky = ty[p], iy = ty[p + 1];
          for (let q = 0; q < tx.length; q += 2) {
            let wb = (go * gin * 16 + ky * 4 + tx[q]) * 16;  // w: [g_out, g_in, tap, j, o]
            for (let g = 0; g < gin; g++, wb += 256) {
              const src = g < ga ? a : b, base = (((g < ga ? g : g - ga) * H + iy) * H + tx[q + 1]) * 4;
              const x0 = src[base], x1 = src[base + 1], x2 = src[base + 2], x3 = src[base + 3];
              s0 += w[wb] * x0 + w[wb + 4] * x1 + w[wb + 8] * x2 + w[wb + 12] * x3;
              s1 += w[wb + 1] * x0 + w[wb + 5] * x1 + w[wb + 9] * x2 + w[wb + 13] * x3;
              s2 += w[wb + 2] * x0 + w[wb + 6] * x1 + w[wb + 10] * x2 + w[wb + 14] * x3;
              s3 += w[wb + 3] * x0 + w[wb + 7] * x1 + w[wb + 11] * x2 + w[wb + 15] * x3;
            }
          }
        }
        acc[0] = s0; acc[1] = s1; acc[2] = s2; acc[3] = s3;
        const o = ((go * OH + oy) * OH + ox) * 4;
        for (let c = 0; c < 4; c++) {
          const v = acc[c] * post[go * 4 + c] + post[G * 4 + go * 4 + c];
          out[o + c] = act === 0 ? (v > 0 ? v : slope * v) : act === 1 ? Math.max(v, 0) : 1 / (1 + Math.exp(-v));
        }
      }
    }
  }
}

// One U-Net: its layers' weights and output buffers, built once; run(input) per frame.
export class CpuUNet {
  constructor(desc, side, arrays) {
    this.ops = [];
    let size = side;
    for (const op of desc.ops) {
      size = op.kind === 'conv' ? size / 2 : size * 2;
      const inSize = op.kind === 'conv' ? size * 2 : size / 2;
      this.ops.push({...op, inSize, outSize: size, w: arrays(op.weights), post: arrays(op.post),
                     taps: tapTable(size, inSize, op.kind === 'convT'),
                     out: new Float32Array(size * size * op.out_groups * 4)});
    }
    this.inGroups = (desc.in_channels + 3) >> 2;
  }

  // input: the stacked temporal normal map (stackChannels' layout); returns the feature maps (groups stacked).
  run(input) {
    const downs = [];
    let a = input, b = null, ga = this.inGroups, gb = 0;
    for (const op of this.ops) {
      convLayer(op, a, ga, b, gb, op.out);
      if (op.kind === 'conv') {
        downs.push(op);
        a = op.out; b = null; ga = op.out_groups; gb = 0;
      } else if (op.skip !== undefined) {
        const skip = downs[op.skip];
        a = op.out; b = skip.out; ga = op.out_groups; gb = skip.out_groups;
      } else {
        a = op.out; ga = op.out_groups; gb = 0; b = null;
      }
    }
    return this.ops[this.ops.length - 1].out;
  }
}
