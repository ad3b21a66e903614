// Which backend draws the avatar: ?backend=webgl2 (the GPU's shaders), ?backend=cpu (plain JavaScript, a 2D
// canvas) or ?backend=auto (the default): WebGL2 where the browser gives a WebGL2 context that renders to float
// textures (EXT_color_buffer_float), else the CPU.

import {WebGL2Backend} from './webgl_backend.js';
import {CpuBackend} from './cpu_backend.js';

export const BACKENDS = ['auto', 'webgl2', 'cpu'];

// Whether this browser has WebGL2 with EXT_color_buffer_float (probed on a canvas of its own: a canvas that has
// had a WebGL2 context cannot give a 2D one).
export function webgl2Available() {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    if (!gl) return false;
    const ok = !!gl.getExtension('EXT_color_buffer_float');
    const lose = gl.getExtension('WEBGL_lose_context');
    if (lose) lose.loseContext();
    return ok;
  } catch (err) {
    return false;
  }
}

// 'webgl2' or 'cpu' for the page's ?backend= (`search`: a location.search string).
export function chooseBackend(search = '') {
  const asked = new URLSearchParams(search).get('backend') || 'auto';
  if (!BACKENDS.includes(asked)) throw new Error(`unknown backend ${asked} (?backend=${BACKENDS.join(', ')})`);
  if (asked !== 'auto') return asked;
  return webgl2Available() ? 'webgl2' : 'cpu';
}

// The backend for `canvas`: {name, encode(windows, normal), raster(inner, outer, cam), shade(hits, cam), sync(),
// hits()}.
export function createBackend(canvas, model, scene, arrays, search = '') {
  const Backend = chooseBackend(search) === 'cpu' ? CpuBackend : WebGL2Backend;
  return new Backend(canvas, model, scene, arrays);
}
