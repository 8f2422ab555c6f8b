// The garmentgnn glTF viewer: plays the morph-target animation of a .glb embedded in
// the page (base64 in <script id="glb" type="application/octet-stream">), so the page
// is one self-contained file that opens from file:// with no server and no network.
// Bundled with three.js by esbuild (make install) and inlined by garmentgnn.viz.viewer.
// URL hash "#t=SECONDS" freezes the animation at that time (used by tests).
// Objects with a "label" in their glTF extras get it shown above them, and a "colorbar"
// in the scene's extras is drawn under the view.  When WebGL or the file fails, the page
// says so in a visible box (and window.__error holds the message).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

function decode(text) {
  const bin = atob(text.trim());
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return bytes.buffer;
}

function fail(msg, what) {
  const text = (what || 'Could not load the model') + ': ' + (msg && msg.message ? msg.message : msg);
  window.__error = text;
  const div = document.getElementById('status');
  if (div) {
    div.textContent = text;
    div.className = 'error';
  }
}

function webglProblem() {
  try {
    const canvas = document.createElement('canvas');
    if (canvas.getContext('webgl2') || canvas.getContext('webgl')) return null;
    return 'this browser has WebGL turned off or cannot create a WebGL context';
  } catch (e) {
    return String(e);
  }
}

function colorbar(bar) {
  const div = document.createElement('div');
  div.id = 'colorbar';
  const stops = bar.colors.map((c, i) => `${c} ${(100 * i) / (bar.colors.length - 1)}%`);
  div.innerHTML = `<div class="title"></div><div class="ramp" style="background:` +
    `linear-gradient(to right, ${stops.join(', ')})"></div>` +
    `<div class="ticks"><span>${bar.min}</span><span>${bar.max}+</span></div>`;
  div.querySelector('.title').textContent = bar.label;
  document.body.appendChild(div);
}

function start() {
  const problem = webglProblem();
  if (problem) {
    fail(problem + '. Open the MP4/PNG beside this page, or this page in a browser with ' +
         'WebGL (hardware acceleration) on.', 'Cannot show the 3D view');
    return;
  }
  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  } catch (e) {
    fail(e, 'Cannot show the 3D view (WebGL failed)');
    return;
  }
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
  const labels = [];  // [object, div]
  const box = new THREE.Box3();
  const top = new THREE.Vector3();
  let labelHeight = 0;  // one row of labels above the whole scene, like the MP4's titles

  function placeLabels() {
    for (const [obj, div] of labels) {
      box.setFromObject(obj);
      box.getCenter(top);
      top.y = labelHeight;
      top.project(camera);
      div.style.left = `${((top.x + 1) / 2) * window.innerWidth}px`;
      div.style.top = `${((1 - top.y) / 2) * window.innerHeight}px`;
      div.style.display = top.z < 1 ? '' : 'none';
    }
  }

  function frame() {
    clock.update();
    if (mixer && fixed === null) mixer.setTime(clock.getElapsed() % Math.max(duration, 1e-6));
    controls.update();
    renderer.render(scene, camera);
    placeLabels();
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
    gltf.scene.traverse((obj) => {
      if (!obj.userData || !obj.userData.label) return;
      const div = document.createElement('div');
      div.className = 'label';
      div.textContent = obj.userData.label;
      document.body.appendChild(div);
      labels.push([obj, div]);
    });
    if (gltf.scene.userData && gltf.scene.userData.colorbar) colorbar(gltf.scene.userData.colorbar);
    const box = new THREE.Box3().setFromObject(gltf.scene);
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    labelHeight = box.max.y + 0.04 * size.y;
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
  }, (e) => fail(e, 'Could not read the glTF model embedded in this page'));
}

start();
