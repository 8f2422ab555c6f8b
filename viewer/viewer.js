// The garmentgnn glTF viewer: plays the morph-target animation of a .glb embedded in
// the page (base64 in <script id="glb" type="application/octet-stream">), so the page
// is one self-contained file that opens from file:// with no server and no network.
// Bundled with three.js by esbuild (make install) and inlined by garmentgnn.viz.viewer.
// URL hash "#t=SECONDS" freezes the animation at that time (used by tests).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

function decode(text) {
  const bin = atob(text.trim());
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return bytes.buffer;
}

function fail(msg) {
  window.__error = String(msg);
  const div = document.getElementById('status');
  if (div) div.textContent = 'could not load the model: ' + msg;
}

function start() {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(window.innerWidth, window.innerHeight);
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xffffff);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 1.8);
  sun.position.set(1, 2, 3);
  scene.add(sun);
  const camera = new THREE.PerspectiveCamera(30, window.innerWidth / window.innerHeight, 0.01, 100);
  const controls = new OrbitControls(camera, renderer.domElement);
  const match = /t=([0-9.]+)/.exec(window.location.hash);
  const fixed = match ? parseFloat(match[1]) : null;
  let mixer = null;
  let duration = 0;
  const clock = new THREE.Timer();
  const status = document.getElementById('status');

  function frame() {
    clock.update();
    if (mixer && fixed === null) mixer.setTime(clock.getElapsed() % Math.max(duration, 1e-6));
    controls.update();
    renderer.render(scene, camera);
    requestAnimationFrame(frame);  // also when frozen: a resize clears the canvas
  }

  window.addEventListener('resize', () => {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
  });

  let data;
  try {
    data = decode(document.getElementById('glb').textContent);
  } catch (e) {
    fail(e);
    return;
  }
  new GLTFLoader().parse(data, '', (gltf) => {
    scene.add(gltf.scene);
    const box = new THREE.Box3().setFromObject(gltf.scene);
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    const fit = Math.max(size.y, size.x / camera.aspect) * 0.5 / Math.tan(THREE.MathUtils.degToRad(15));
    camera.position.set(centre.x, centre.y + 0.1 * size.y, centre.z + 1.2 * fit + 0.5 * size.z);
    controls.target.copy(centre);
    if (gltf.animations.length) {
      mixer = new THREE.AnimationMixer(gltf.scene);
      for (const clip of gltf.animations) {
        // hold the last key for one frame step: a looping clip ends at its last key's
        // time and would wrap to frame 0 there, never showing the last frame
        const times = clip.tracks.length ? clip.tracks[0].times : [];
        if (times.length > 1) clip.duration = times[times.length - 1] + (times[1] - times[0]);
        mixer.clipAction(clip).play();
        duration = Math.max(duration, clip.duration);
      }
      mixer.setTime(fixed === null ? 0 : fixed);
    }
    if (status) status.textContent = (window.__title || '') + (gltf.animations.length ?
      ' (drag to turn, scroll to zoom)' : '');
    frame();
    window.__ready = true;
  }, fail);
}

start();
