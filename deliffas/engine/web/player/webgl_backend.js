// The WebGL2 backend: U-Nets (unet.js), rasterisation (raster.js) and the light field (shade.js) as shader passes
// over RGBA32F textures (EXT_color_buffer_float), drawn to the canvas's WebGL2 context.

import {createContext, describeRenderer, floatTexture, renderTarget, unetInputTexels, unetSide, uploadTexture}
  from './gl.js';
import {UNetPasses} from './unet.js';
import {SurfaceRaster} from './raster.js';
import {LightFieldPass} from './shade.js';

export class WebGL2Backend {
  constructor(canvas, model, scene, arrays) {
    const gl = this.gl = createContext(canvas);
    this.name = `webgl2 (${describeRenderer(gl)})`;
    this.model = model;
    const S = model.atlas_res, SU = unetSide(model);  // the atlas side, the U-Nets' side
    this.vao = gl.createVertexArray();
    this.unets = {inner: new UNetPasses(gl, model.unet_inner, SU, arrays, this.vao),
                  outer: model.unet_outer ? new UNetPasses(gl, model.unet_outer, SU, arrays, this.vao) : null};
    const channels = 3 * (model.temporal_window + 1), groups = (channels + 3) >> 2;
    this.input = {channels, pooled: SU < S ? new Float32Array(channels * SU * SU) : null,
                  buffer: new Float32Array(groups * SU * SU * 4),
                  inner: floatTexture(gl, SU, SU * groups), outer: floatTexture(gl, SU, SU * groups)};
    const atlas = t => (t ? floatTexture(gl, S, S * ((t.channels + 3) >> 2), arrays(t.data)) : floatTexture(gl, 1, 1));
    this.maps = {innerT: atlas(model.texture_inner), outerT: atlas(model.texture_outer),
                 normal: floatTexture(gl, S, S)};
    const table = model.mlp.table;
    this.shadePass = new LightFieldPass(gl, model, floatTexture(gl, table.shape[1] / 4, table.shape[0], arrays(table)),
                                        this.vao);
    this.syncTarget = renderTarget(gl, 1, 1);
    this.syncPixel = new Float32Array(4);
    this.rasterPass = new SurfaceRaster(gl, arrays(scene.faces), arrays(scene.uvs), arrays(scene.face_uvs));
  }

  // The U-Nets on the temporal windows of both surfaces' normal maps ((3 (T + 1), S, S) each, pooled to the U-Nets'
  // side); normal: the inner normal map as S x S RGBA texels (the reflection's normals).
  encode(windows, normal) {
    const gl = this.gl, inp = this.input;
    uploadTexture(gl, this.maps.normal, normal);
    uploadTexture(gl, inp.inner, unetInputTexels(this.model, windows[0], inp));
    this.maps.innerF = this.unets.inner.run(inp.inner);
    if (this.unets.outer) {
      uploadTexture(gl, inp.outer, unetInputTexels(this.model, windows[1], inp));
      this.maps.outerF = this.unets.outer.run(inp.outer);
    } else {
      this.maps.outerF = this.maps.innerF;
    }
  }

  raster(inner, outer, cam) { return this.rasterPass.run(inner, outer, cam); }

  shade(hits, cam) { this.shadePass.run(hits, this.maps, cam); }

  // Wait until the GPU has done every command so far: a one-pixel read (gl.finish need not wait in a browser).
  sync() {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.syncTarget.fb);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.FLOAT, this.syncPixel);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  // The raster targets of the last draw, {inner, outer, exit}: (H * W * 4) floats (u, v, z, hit), rows bottom up.
  hits() {
    const gl = this.gl, out = {};
    for (const [name, t] of Object.entries(this.rasterPass.targets)) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
      const data = new Float32Array(t.w * t.h * 4);
      gl.readPixels(0, 0, t.w, t.h, gl.RGBA, gl.FLOAT, data);
      out[name] = Array.from(data);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return out;
  }
}
