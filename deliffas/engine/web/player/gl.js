// WebGL2 helpers: the context, float textures and render targets, programs, the full-screen triangle.

export const FULLSCREEN_VS = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

export function createContext(canvas) {
  const gl = canvas.getContext('webgl2', {preserveDrawingBuffer: true, antialias: false, alpha: false,
                                          depth: false, premultipliedAlpha: false});
  if (!gl) throw new Error('this browser has no WebGL2');
  if (!gl.getExtension('EXT_color_buffer_float')) throw new Error('this browser cannot render to float textures '
                                                                   + '(EXT_color_buffer_float)');
  return gl;
}

export function describeRenderer(gl) {
  const info = gl.getExtension('WEBGL_debug_renderer_info');
  return info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}

// An RGBA32F texture of w x h texels, nearest filtering (read with texelFetch); data: Float32Array or null.
export function floatTexture(gl, w, h, data = null) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, w, h);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  for (const p of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T]) gl.texParameteri(gl.TEXTURE_2D, p, gl.CLAMP_TO_EDGE);
  if (data) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, w, h, gl.RGBA, gl.FLOAT, data);
  return {tex, w, h};
}

export function uploadTexture(gl, t, data) {
  gl.bindTexture(gl.TEXTURE_2D, t.tex);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, t.w, t.h, gl.RGBA, gl.FLOAT, data);
}

// A float texture with a framebuffer (and a 32-bit depth buffer when depth is set).
export function renderTarget(gl, w, h, depth = false) {
  const t = floatTexture(gl, w, h);
  t.fb = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t.tex, 0);
  if (depth) {
    t.depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, t.depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT32F, w, h);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, t.depth);
  }
  const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
  if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`float render target incomplete (${status})`);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  return t;
}

export function deleteTarget(gl, t) {
  gl.deleteTexture(t.tex);
  if (t.fb) gl.deleteFramebuffer(t.fb);
  if (t.depth) gl.deleteRenderbuffer(t.depth);
}

function compile(gl, type, source) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
    throw new Error(`shader does not compile: ${gl.getShaderInfoLog(s)}\n${source}`);
  }
  return s;
}

// A linked program with its uniform locations looked up by name (prog.u.name).
export function program(gl, vs, fs) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vs));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program does not link: ${gl.getProgramInfoLog(p)}`);
  const u = {};
  const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(p, i).name.replace(/\[0\]$/, '');
    u[name] = gl.getUniformLocation(p, name);
  }
  return {p, u};
}

// Bind textures to units in order: bindTextures(gl, prog, {uA: tex, ...}).
export function bindTextures(gl, prog, textures) {
  let unit = 0;
  for (const [name, t] of Object.entries(textures)) {
    if (!(name in prog.u)) continue;
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, t.tex);
    gl.uniform1i(prog.u[name], unit++);
  }
}

export function drawFullscreen(gl, target, vao) {
  gl.bindFramebuffer(gl.FRAMEBUFFER, target ? target.fb : null);
  gl.viewport(0, 0, target ? target.w : gl.drawingBufferWidth, target ? target.h : gl.drawingBufferHeight);
  gl.bindVertexArray(vao);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
}

// The U-Nets' input side of a model: the atlas side S over unet_downsample (S itself without one).
export function unetSide(model) {
  return model.atlas_res / (model.unet_downsample || 1);
}

// A channel-first array (c, side, side) of `channels` channels average-pooled by d (F.avg_pool2d(x, d): the mean of
// each d x d block of texels): (c, side / d, side / d); `src` itself for d = 1.
export function poolChannels(src, channels, side, d, out = null) {
  if (d === 1) return src;
  const m = side / d, dst = out || new Float32Array(channels * m * m), inv = 1 / (d * d);
  for (let c = 0; c < channels; c++) {
    const s = c * side * side, o = c * m * m;
    for (let y = 0; y < m; y++) {
      for (let x = 0; x < m; x++) {
        let sum = 0;
        for (let j = 0; j < d; j++) for (let i = 0; i < d; i++) sum += src[s + (y * d + j) * side + x * d + i];
        dst[o + y * m + x] = sum * inv;
      }
    }
  }
  return dst;
}

// One surface's temporal window (3 (T + 1), S, S) as the U-Nets' input texels: pooled by unet_downsample into
// input.pooled, channels stacked into input.buffer ({channels, pooled, buffer}, as both backends hold them).
export function unetInputTexels(model, window, input) {
  const S = model.atlas_res, SU = unetSide(model);
  return stackChannels(poolChannels(window, input.channels, S, S / SU, input.pooled), input.channels, SU,
                       input.buffer);
}

// Float32Array of w x h RGBA texels holding `groups` stacked maps (rows g*side .. g*side+side-1) from a
// channel-first array (c, side, side) of `channels` channels: channel c goes to group c >> 2, component c & 3.
export function stackChannels(src, channels, side, out = null) {
  const groups = (channels + 3) >> 2, n = side * side;
  const dst = out || new Float32Array(groups * n * 4);
  dst.fill(0);
  for (let c = 0; c < channels; c++) {
    const base = (c >> 2) * n * 4 + (c & 3), s = c * n;
    for (let i = 0; i < n; i++) dst[base + 4 * i] = src[s + i];
  }
  return dst;
}
