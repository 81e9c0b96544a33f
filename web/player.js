// The volcap player: a recorded volumetric sequence played at its capture timing, or the newest
// mesh of a running graph pushed over a WebSocket. The GLBs are glTF 2.0 (+Y up, linear vertex
// colour, unlit), meshopt- or Draco-compressed; three.js decodes them.
//
// window.volcap reports what the page is doing (tests and operators read it): mode, frames shown,
// the current frame's index and capture stamp, and decode times.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { DRACOLoader } from 'three/addons/loaders/DRACOLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';

const hud = document.getElementById('hud');
const state = window.volcap = { mode: null, ready: false, shown: 0, index: null, stamp_ns: null,
                                decodeMs: [], frames: 0, error: null, hud: null };

const canvas = document.getElementById('view');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.outputColorSpace = THREE.SRGBColorSpace;      // linear vertex colour in, sRGB on screen
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x30343a);
scene.add(new THREE.GridHelper(4, 8, 0x666b73, 0x4a4f57));   // the studio floor, 50 cm squares
const camera = new THREE.PerspectiveCamera(40, 1, 0.05, 50);
camera.position.set(0, 1.2, 3.6);                      // in front of the subject (glTF front: +Z)
const controls = new OrbitControls(camera, canvas);
controls.target.set(0, 0.9, 0);
controls.update();
// The view in glTF coordinates, for a test to render the same view of the ground truth.
state.camera = () => ({ position: camera.position.toArray(), target: controls.target.toArray(), fov: camera.fov,
                        width: canvas.width, height: canvas.height });
state.hud = on => { hud.style.display = on ? '' : 'none'; };

const draco = new DRACOLoader().setDecoderPath('/node_modules/three/examples/jsm/libs/draco/gltf/');
const loader = new GLTFLoader().setMeshoptDecoder(MeshoptDecoder).setDRACOLoader(draco);

function resize() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();

function fail(message) {
  state.error = message;
  hud.textContent = message;
  hud.className = 'error';
}

// GLB bytes -> a scene graph ready to draw, and the frame's extras (index, capture stamp).
async function decode(buffer) {
  await MeshoptDecoder.ready;
  const t0 = performance.now();
  const gltf = await loader.parseAsync(buffer, '');
  state.decodeMs.push(performance.now() - t0);
  if (state.decodeMs.length > 1000) state.decodeMs.splice(0, state.decodeMs.length - 1000);   // a long take: bounded
  return { root: gltf.scene, extras: (gltf.scene.userData || {}).volcap || {} };
}

let current = null;
let framed = false;
function show(frame) {
  if (current) {
    scene.remove(current.root);
    current.root.traverse(o => { if (o.geometry) o.geometry.dispose(); if (o.material) o.material.dispose(); });
  }
  current = frame;
  scene.add(frame.root);
  if (!framed) {          // look at the subject once; the operator's orbit is kept after that
    const box = new THREE.Box3().setFromObject(frame.root);
    if (!box.isEmpty()) {
      const centre = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3());
      controls.target.copy(centre);
      const distance = 1.25 * Math.max(size.y, size.x) / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
      camera.position.set(centre.x, centre.y + 0.1 * size.y, centre.z + Math.max(distance, 1.0));
      controls.update();
      framed = true;
    }
  }
  state.shown += 1;
  state.index = frame.extras.index ?? null;
  state.stamp_ns = frame.extras.stamp_ns ?? null;
  state.ready = true;
}

function status(extra) {
  const ms = state.decodeMs.slice(-30);
  const mean = ms.length ? ms.reduce((a, b) => a + b, 0) / ms.length : 0;
  hud.textContent = `${extra}\nframe ${state.index ?? '-'}  stamp ${state.stamp_ns ?? '-'}\n` +
                    `decode ${mean.toFixed(1)} ms (mean of the last ${ms.length})`;
}

// A recorded sequence: /sequence/manifest.json and /sequence/sequence.jsonl, frames fetched and
// decoded ahead of the clock, shown when their capture time comes.
async function playSequence() {
  state.mode = 'sequence';
  const response = await fetch('/sequence/sequence.jsonl', { cache: 'no-store' });
  if (!response.ok) return fail(`no sequence.jsonl (${response.status})`);
  const frames = (await response.text()).split('\n').filter(Boolean).map(line => {
    try { return JSON.parse(line); } catch { return null; }       // a line still being written
  }).filter(doc => doc && doc.glb !== undefined && doc.index !== undefined);
  if (!frames.length) return fail('the sequence has no GLB frames');
  state.frames = frames.length;
  const manifest = await (await fetch('/sequence/manifest.json', { cache: 'no-store' })).json().catch(() => ({}));
  const rate = manifest.frame_rate || 30;
  const t0 = BigInt(frames[0].stamp_ns);
  const offsets = frames.map(f => Number(BigInt(f.stamp_ns) - t0) / 1e6);   // ms from the first frame
  const duration = offsets[offsets.length - 1] + 1000 / rate;
  const ahead = new Map();
  const load = k => {
    if (!ahead.has(k)) ahead.set(k, fetch(`/sequence/${frames[k].glb}`).then(r => r.arrayBuffer()).then(decode));
    return ahead.get(k);
  };
  let k = 0;
  let start = performance.now();
  for (;;) {
    const frame = await load(k);
    for (let j = 1; j <= 3; j++) load((k + j) % frames.length);      // decode ahead of the clock
    const due = start + offsets[k];
    const wait = due - performance.now();
    if (wait > 0) await new Promise(r => setTimeout(r, wait));
    show(frame);
    ahead.delete(k);
    status(`sequence: ${frames.length} frames at ${rate.toFixed(1)} fps (${manifest.glb_encoding || '?'})`);
    k += 1;
    if (k === frames.length) { k = 0; start += duration; }
    if (performance.now() - start > offsets[k] + 1000) start = performance.now() - offsets[k];  // fell behind: skip ahead in time
  }
}

// A running graph: the newest GLB pushed over the WebSocket the server names in /config.json.
async function playLive(url) {
  state.mode = 'live';
  let busy = false, pending = null;
  const socket = new WebSocket(url);
  socket.binaryType = 'arraybuffer';
  const next = async () => {
    if (busy || !pending) return;
    busy = true;
    const buffer = pending; pending = null;
    try { show(await decode(buffer)); status(`live: ${url}`); } catch (e) { fail(`undecodable frame: ${e}`); }
    busy = false;
    next();
  };
  socket.onmessage = ev => { pending = ev.data; next(); };      // only the newest frame waits
  socket.onopen = () => status(`live: ${url}, waiting for the first mesh`);
  socket.onclose = () => fail(`live stream closed (${url}); reload to reconnect`);
}

function animate() {
  controls.update();
  renderer.render(scene, camera);
  requestAnimationFrame(animate);
}
animate();

const config = await (await fetch('/config.json', { cache: 'no-store' })).json();
(config.live ? playLive(config.live) : playSequence()).catch(e => fail(String(e)));
