// The CPU backend, for browsers without WebGL2 or EXT_color_buffer_float (or ?backend=cpu): the same U-Nets,
// rasterisation and light field as the WebGL2 backend in plain JavaScript over typed arrays (cpu_unet.js,
// cpu_raster.js, cpu_shade.js), drawn to the canvas's 2D context with putImageData.

import {unetInputTexels, unetSide} from './gl.js';
import {CpuUNet} from './cpu_unet.js';
import {CpuRaster} from './cpu_raster.js';
import {CpuLightField} from './cpu_shade.js';

export class CpuBackend {
  constructor(canvas, model, scene, arrays) {
    this.ctx = canvas.getContext('2d', {alpha: false});
    if (!this.ctx) throw new Error('this browser gives the canvas neither WebGL2 nor a 2D context');
    this.name = 'cpu';
    this.canvas = canvas;
    this.model = model;
    const S = model.atlas_res, SU = unetSide(model);  // the atlas side, the U-Nets' side
    this.unets = {inner: new CpuUNet(model.unet_inner, SU, arrays),
                  outer: model.unet_outer ? new CpuUNet(model.unet_outer, SU, arrays) : null};
    const channels = 3 * (model.temporal_window + 1);
    this.input = {channels, pooled: SU < S ? new Float32Array(channels * SU * SU) : null,
                  buffer: new Float32Array(((channels + 3) >> 2) * SU * SU * 4)};
    const atlas = t => (t ? arrays(t.data) : null);
    this.maps = {innerT: atlas(model.texture_inner), outerT: atlas(model.texture_outer), normal: null};
    this.shadePass = new CpuLightField(model, arrays(model.mlp.table));
    this.rasterPass = new CpuRaster(arrays(scene.faces), arrays(scene.uvs), arrays(scene.face_uvs));
    this.image = null;
  }

  // As WebGL2Backend.encode: the feature maps as stacked Float32Arrays.
  encode(windows, normal) {
    this.maps.normal = normal;
    const input = w => unetInputTexels(this.model, w, this.input);
    this.maps.innerF = this.unets.inner.run(input(windows[0]));
    this.maps.outerF = this.unets.outer ? this.unets.outer.run(input(windows[1])) : this.maps.innerF;
  }

  raster(inner, outer, cam) { return this.rasterPass.run(inner, outer, cam); }

  shade(hits, cam) {
    if (!this.image || this.image.width !== cam.width || this.image.height !== cam.height) {
      this.image = this.ctx.createImageData(cam.width, cam.height);
    }
    this.shadePass.run(hits, this.maps, cam, this.image.data);
    this.ctx.putImageData(this.image, 0, 0);
  }

  sync() {}

  // As WebGL2Backend.hits: rows bottom up.
  hits() {
    const out = {};
    for (const [name, t] of Object.entries(this.rasterPass.targets)) {
      const rows = [];
      for (let y = t.h - 1; y >= 0; y--) rows.push(...t.data.subarray(y * t.w * 4, (y + 1) * t.w * 4));
      out[name] = rows;
    }
    return out;
  }
}
