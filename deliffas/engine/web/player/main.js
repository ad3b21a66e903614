// The player: loads avatar.json and avatar.bin, renders a frame from a camera (posing and normal maps on the
// CPU; U-Nets, rasterisation with depth peeling and the light field on the GPU with WebGL2, or on the CPU: see
// backend.js), plays the motion, and exposes the test hook window.deliffasPlayer = {ready, render({frame, camera}),
// stats()}.

import {FrameGeometry} from './geometry.js';
import {createBackend} from './backend.js';
import {OrbitCamera} from './orbit.js';
import {bindControls} from './ui.js';

const TYPES = {float32: Float32Array, int32: Int32Array, uint8: Uint8Array};

async function loadAvatar() {
  const [index, bin] = await Promise.all([fetch('avatar.json').then(r => r.json()),
                                         fetch('avatar.bin').then(r => r.arrayBuffer())]);
  const arrays = e => new TYPES[e.dtype](bin, e.offset, e.shape.reduce((a, b) => a * b, 1));
  return {index, arrays};
}

class Player {
  constructor(canvas, index, arrays) {
    this.canvas = canvas;
    const model = this.model = index.model, scene = index.scene, S = model.atlas_res;
    this.engine = createBackend(canvas, model, scene, arrays, location.search);
    this.backend = this.engine.name;
    this.geometry = new FrameGeometry(scene, arrays, S);
    this.cameras = scene.cameras;
    const test = scene.test_cameras.length ? scene.test_cameras[0] : 0;
    const first = this.geometry.get(0).inner, center = [0, 1, 2].map(i => {
      let s = 0;
      for (let v = i; v < first.length; v += 3) s += first[v];
      return s / (first.length / 3);
    });
    this.orbit = new OrbitCamera(this.cameras[test], center);
    this.camera = 'orbit';
    this.frame = 0;
    this.encoded = -1;
    this.playing = true;
    this.times = [];
    this.stages = {};
    this.onFrame = null;
  }

  get numFrames() { return this.geometry.numFrames; }

  encode(frame, timed) {
    if (this.encoded === frame) return;
    const S = this.model.atlas_res, T = this.model.temporal_window;
    const normals = timed('normal_maps', () => {
      const g = this.geometry.get(frame);
      const windows = ['inner', 'outer'].map(s => this.geometry.window(frame, T, s === 'inner' ? 'nmInner' : 'nmOuter'));
      const n = new Float32Array(S * S * 4);
      for (let t = 0; t < S * S; t++) for (let c = 0; c < 3; c++) n[4 * t + c] = g.nmInner[c * S * S + t];
      return {windows, n};
    });
    timed('unet', () => this.engine.encode(normals.windows, normals.n));
    this.encoded = frame;
  }

  // Draw `frame` seen by `cam` ({K, world_to_cam, width, height}); profile: wait for the backend after each stage.
  draw(frame, cam, profile = false) {
    const stages = {};
    const timed = (name, fn) => {
      const t0 = performance.now(), out = fn();
      if (profile) this.sync();
      stages[name] = (stages[name] || 0) + performance.now() - t0;
      return out;
    };
    if (this.canvas.width !== cam.width || this.canvas.height !== cam.height) {
      this.canvas.width = cam.width;
      this.canvas.height = cam.height;
    }
    this.encode(frame, timed);
    const g = timed('pose', () => this.geometry.get(frame));
    const hits = timed('raster', () => this.engine.raster(g.inner, g.outer, cam));
    timed('shade', () => this.engine.shade(hits, cam));
    this.stages = stages;
  }

  // Wait until the backend has done every command so far (the GPU's: a one-pixel read; the CPU's: done).
  sync() { this.engine.sync(); }

  currentCamera() { return this.camera === 'orbit' ? this.orbit.camera() : this.cameras[this.camera]; }

  useCamera(which) { this.camera = which; this.show(this.frame); }

  show(frame) {
    this.frame = frame;
    this.draw(frame, this.currentCamera());
    if (this.onFrame) this.onFrame();
  }

  tick(now) {
    if (this.playing) {
      this.times.push(now);
      if (this.times.length > 30) this.times.shift();
      this.show((this.frame + 1) % this.numFrames);
    } else {
      this.times = [];
    }
    requestAnimationFrame(t => this.tick(t));
  }

  stats() {
    const t = this.times, n = t.length;
    const fps = n > 1 ? (n - 1) * 1000 / (t[n - 1] - t[0]) : 0;
    return {fps, backend: this.backend, stages_ms: {...this.stages}, frames: this.numFrames};
  }

  // The test hook: render `frame` from capture camera `camera`, resolved once it is on the canvas.
  async render({frame, camera}) {
    this.playing = false;
    this.camera = camera;
    this.frame = frame;
    const t0 = performance.now();
    this.draw(frame, this.cameras[camera], true);
    this.sync();
    if (this.onFrame) this.onFrame();
    await new Promise(r => requestAnimationFrame(() => r()));
    return {width: this.canvas.width, height: this.canvas.height, ms: performance.now() - t0};
  }

  // The raster targets of the last draw, {inner, outer, exit}: (H * W * 4) floats (u, v, z, hit), rows bottom up.
  hits() { return this.engine.hits(); }

  // Play `count` frames from capture camera `camera` (or the orbit), each posed anew (its predecessors in the
  // temporal window stay cached, as in playback) and waited for: {fps, stages_ms} (stages: mean per frame,
  // measured with a wait after each stage, so only with profile).
  async benchmark(count = 20, camera = 'orbit', profile = false) {
    this.playing = false;
    const cam = camera === 'orbit' ? this.orbit.camera() : this.cameras[camera];
    const total = {};
    const t0 = performance.now();
    for (let i = 0; i < count; i++) {
      const frame = i % this.numFrames;
      this.geometry.cache.delete(frame);
      this.draw(frame, cam, profile);
      this.sync();
      for (const [k, v] of Object.entries(this.stages)) total[k] = (total[k] || 0) + v / count;
    }
    const fps = count * 1000 / (performance.now() - t0);
    return {fps, stages_ms: profile ? total : {}};
  }

}

function fail(message) {
  const box = document.getElementById('message');
  box.textContent = message;
  box.hidden = false;
}

const ready = (async () => {
  const t0 = performance.now();
  const {index, arrays} = await loadAvatar();
  const player = new Player(document.getElementById('view'), index, arrays);
  player.show(0);
  player.sync();
  player.firstFrameMs = performance.now() - t0;
  bindControls(player);
  requestAnimationFrame(t => player.tick(t));
  return player;
})();
ready.catch(err => fail(`the player could not start: ${err.message}`));

window.deliffasPlayer = {
  ready: ready.then(() => true),
  render: async args => (await ready).render(args),
  stats: () => (window.__deliffasStats ? window.__deliffasStats() : {fps: 0, backend: 'loading'}),
  benchmark: async (count, camera, profile) => (await ready).benchmark(count, camera, profile),
  firstFrameMs: async () => (await ready).firstFrameMs,
  hits: async () => (await ready).hits(),
  geometry: async frame => {
    const g = (await ready).geometry.get(frame);
    return {inner: Array.from(g.inner), outer: Array.from(g.outer), nmInner: Array.from(g.nmInner)};
  },
};
ready.then(p => { window.__deliffasStats = () => p.stats(); });
