// The page's controls: frame slider, play/pause, camera menu, fps readout, and the orbit drag and zoom.

export function bindControls(player, doc = document) {
  const slider = doc.getElementById('frame'), play = doc.getElementById('play');
  const select = doc.getElementById('camera'), fps = doc.getElementById('fps'), canvas = doc.getElementById('view');
  slider.max = String(player.numFrames - 1);
  select.add(new Option('orbit (drag to turn, wheel to zoom)', 'orbit'));
  player.cameras.forEach((c, i) => select.add(new Option(`capture camera ${i} (${c.name})`, String(i))));
  select.value = 'orbit';
  const show = () => {
    slider.value = String(player.frame);
    play.textContent = player.playing ? 'pause' : 'play';
    const s = player.stats();
    fps.textContent = `${s.fps.toFixed(1)} fps · frame ${player.frame + 1}/${player.numFrames} · ${s.backend}`;
  };
  player.onFrame = show;
  slider.addEventListener('input', () => { player.playing = false; player.show(Number(slider.value)); });
  play.addEventListener('click', () => { player.playing = !player.playing; show(); });
  select.addEventListener('change', () => {
    player.useCamera(select.value === 'orbit' ? 'orbit' : Number(select.value));
  });
  let last = null;
  canvas.addEventListener('pointerdown', e => { last = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener('pointerup', () => { last = null; });
  canvas.addEventListener('pointermove', e => {
    if (!last) return;
    player.orbit.drag(e.clientX - last[0], e.clientY - last[1]);
    last = [e.clientX, e.clientY];
    select.value = 'orbit';
    player.useCamera('orbit');
  });
  canvas.addEventListener('wheel', e => {
    e.preventDefault();
    player.orbit.zoom(e.deltaY > 0 ? 1.1 : 1 / 1.1);
    player.useCamera('orbit');
  }, {passive: false});
  show();
}
