// splatcli's web viewer: Spark (vendor/) draws the Gaussians; this file places the camera,
// lists the project's cameras and follows a training run. Served by splatcli/viewer/server.py, or
// as files by any static server (`export --format web`, viewer/site.py): there api/scene is a file
// with "static": true and "splats" (the scene as .sog); the page then neither polls nor shows points.
// URL options: ?camera=NAME starts at that project camera; &hud=0 hides the panel.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
if (params.get("hud") === "0") $("hud").style.display = "none";
// For the tests (tests/support/browser.py): whether the scene has been drawn, and when (ms since navigation start).
window.splatcli = { ready: false, firstFrameMs: null, version: 0, error: null, marks: { script: performance.now() } };

const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1); // one canvas pixel per image pixel, as `splatcli render` draws
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
// Frames are drawn on demand (a camera move, a new scene, Spark's sort finishing), not
// 60 times a second: an idle viewer costs no CPU, which matters beside `train --viewer`.
let queued = false;
function requestRender() {
  if (!queued) { queued = true; requestAnimationFrame(drawFrame); }
}
scene.add(new SparkRenderer({ renderer, onDirty: requestRender }));
const camera = new THREE.PerspectiveCamera(50, innerWidth / innerHeight, 0.01, 1e4);
let controls = null;
let state = null; // api/scene
let current = null; // the project camera in use, or null for a free view
let mesh = null, points = null, mode = "color";

function fail(msg) {
  window.splatcli.error = String(msg);
  $("error").textContent = String(msg);
}

function makeControls(target) {
  if (controls) controls.dispose();
  controls = new OrbitControls(camera, renderer.domElement); // orbits about camera.up, read here
  controls.target.copy(target);
  controls.update(); // its constructor looked at the origin: look at the target again (on the view axis: no change)
  controls.addEventListener("change", requestRender);
  controls.addEventListener("start", () => { current = null; $("cams").value = ""; setProjection(); });
}

// Intrinsics to an OpenGL projection: pixel (u, v) of K maps to the same canvas pixel,
// centres at (u + 0.5, v + 0.5), the picture scaled to the canvas height and centred.
function setProjection() {
  const W = innerWidth, H = innerHeight, n = camera.near, f = camera.far;
  if (!current) { camera.aspect = W / H; camera.updateProjectionMatrix(); requestRender(); return; }
  const c = current, s = H / c.height;
  const fx = c.K[0] * s, fy = c.K[4] * s, cx = c.K[2] * s + (W - c.width * s) / 2, cy = c.K[5] * s;
  camera.fov = THREE.MathUtils.radToDeg(2 * Math.atan(H / (2 * fy)));
  camera.aspect = (W / H) * (fy / fx);
  camera.projectionMatrix.set(
    2 * fx / W, 0, 1 - 2 * cx / W, 0,
    0, 2 * fy / H, 2 * cy / H - 1, 0,
    0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
    0, 0, -1, 0);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  requestRender();
}

// A project camera: viewmat is world-to-camera in OpenCV axes (x right, y down, z forward);
// three's camera looks down -z with y up, so camera-to-world gains a flip of y and z.
function useCamera(c) {
  const V = new THREE.Matrix4().fromArray(c.viewmat).transpose();
  const camToWorld = V.clone().invert().multiply(new THREE.Matrix4().makeScale(1, -1, -1));
  camToWorld.decompose(camera.position, camera.quaternion, new THREE.Vector3());
  camera.up.set(-c.viewmat[4], -c.viewmat[5], -c.viewmat[6]); // the camera's own up: no roll when orbiting
  const forward = new THREE.Vector3(c.viewmat[8], c.viewmat[9], c.viewmat[10]);
  const centre = new THREE.Vector3(...(state.center || [0, 0, 0]));
  const dist = Math.max(centre.clone().sub(camera.position).dot(forward), 1e-3);
  current = c;
  camera.updateMatrixWorld(true);
  makeControls(camera.position.clone().addScaledVector(forward, dist));
  setProjection();
}

function freeView() {
  current = null;
  const centre = new THREE.Vector3(...(state.center || [0, 0, 0]));
  const r = state.radius || 1;
  camera.up.set(...state.up);
  const up = camera.up.clone().normalize();
  const side = Math.abs(up.x) < 0.9 ? new THREE.Vector3(1, 0, 0) : new THREE.Vector3(0, 0, 1);
  const dir = side.sub(up.clone().multiplyScalar(side.dot(up))).normalize().add(up.clone().multiplyScalar(0.4));
  camera.position.copy(centre).addScaledVector(dir.normalize(), 2.5 * r);
  camera.lookAt(centre);
  makeControls(centre);
  setProjection();
}

function resetView() {
  const first = state.cameras.find((c) => c.split === "test") || state.cameras[0];
  if (first) { useCamera(first); $("cams").value = first.name; } else freeView();
}

function fillCameras() {
  const sel = $("cams");
  for (const split of ["train", "test"]) {
    const cams = state.cameras.filter((c) => c.split === split);
    if (!cams.length) continue;
    const g = document.createElement("optgroup");
    g.label = `${split} (${cams.length})`;
    for (const c of cams) g.appendChild(new Option(c.name, c.name));
    sel.appendChild(g);
  }
  sel.onchange = () => {
    const c = state.cameras.find((x) => x.name === sel.value);
    if (c) useCamera(c); else freeView();
  };
}

function showFacts() {
  const mb = state.file_bytes ? `${(state.file_bytes / 1e6).toFixed(2)} MB file (${(state.ply_bytes / 1e6).toFixed(2)} MB as .ply)`
    : `${(state.ply_bytes / 1e6).toFixed(2)} MB as .ply`;
  $("source").textContent = state.source;
  $("facts").textContent = `${state.num_gaussians.toLocaleString()} Gaussians · SH degree ${state.sh_degree} · ` +
    `${mb} · ${state.cameras.length} cameras`;
  const L = state.live || {};
  const parts = [];
  if (L.step !== undefined && L.step !== null) parts.push(`step ${L.step}`);
  if (L.loss !== undefined) parts.push(`loss ${L.loss}`);
  if (L.psnr !== undefined) parts.push(`held-out PSNR ${L.psnr} dB`);
  $("live").textContent = parts.join(" · ");
}

async function loadSplats(version) {
  const url = state.splats || "api/scene.ply";
  const m = new SplatMesh({ url: `${url}?v=${version}`, fileName: url.split("/").pop() });
  await m.initialized;
  window.splatcli.marks.splats = window.splatcli.marks.splats || performance.now();
  scene.add(m);
  if (mesh) { scene.remove(mesh); mesh.dispose(); }
  mesh = m;
  mesh.visible = mode === "color";
  requestRender();
}

function srgbToLinear(x) { return x <= 0.04045 ? x / 12.92 : Math.pow((x + 0.055) / 1.055, 2.4); }

async function loadPoints() {
  const buf = await (await fetch(`api/points.bin?v=${window.splatcli.version}`)).arrayBuffer();
  const n = new DataView(buf).getUint32(0, true);
  const xyz = new Float32Array(buf, 4, 3 * n);
  const rgba = new Uint8Array(buf, 4 + 12 * n, 4 * n);
  const col = new Float32Array(3 * n);
  for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) col[3 * i + k] = srgbToLinear(rgba[4 * i + k] / 255);
  const geo = new THREE.BufferGeometry();
  geo.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  geo.setAttribute("color", new THREE.BufferAttribute(col, 3));
  if (points) { scene.remove(points); points.geometry.dispose(); }
  points = new THREE.Points(geo, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true }));
  scene.add(points);
}

async function setMode(m) {
  mode = m;
  if (m === "points" && (!points || points.userData.version !== window.splatcli.version)) {
    await loadPoints();
    points.userData.version = window.splatcli.version;
  }
  if (points) points.visible = m === "points";
  if (mesh) mesh.visible = m === "color";
  requestRender();
}

// The first frame with the scene in it: pixels in the middle of the canvas that differ from the background.
const probe = new Uint8Array(4 * 64 * 64);
function sceneDrawn() {
  const gl = renderer.getContext();
  const x = Math.max(0, (gl.drawingBufferWidth >> 1) - 32), y = Math.max(0, (gl.drawingBufferHeight >> 1) - 32);
  gl.readPixels(x, y, 64, 64, gl.RGBA, gl.UNSIGNED_BYTE, probe);
  const bg = state.background.map((v) => Math.round(v * 255));
  for (let i = 0; i < probe.length; i += 4) {
    if (Math.abs(probe[i] - bg[0]) + Math.abs(probe[i + 1] - bg[1]) + Math.abs(probe[i + 2] - bg[2]) > 12) return true;
  }
  return false;
}

// While training runs, the page asks every 2 s (the server has a new model every 3 s), or less often when loading and drawing one
// takes long (WebGL on the CPU, beside the training): at most a fifth of the time goes to it.
async function poll() {
  let wait = 2000;
  try {
    const s = await (await fetch("api/scene", { cache: "no-store" })).json();
    if (s.version !== window.splatcli.version && s.num_gaussians > 0) {
      state.live = s.live; state.num_gaussians = s.num_gaussians; state.sh_degree = s.sh_degree;
      state.ply_bytes = s.ply_bytes;
      window.splatcli.version = s.version;
      showFacts();
      const t0 = performance.now();
      await loadSplats(s.version);
      if (mode === "points") await setMode("points");
      renderer.render(scene, camera); // timed to the end of drawing (readPixels waits for it)
      const gl = renderer.getContext();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, probe.subarray(0, 4));
      wait = Math.max(wait, 5 * (performance.now() - t0));
    }
  } catch (e) { /* the server stopped (training ended): keep the last picture */ }
  setTimeout(poll, wait);
}

function drawFrame() {
  queued = false;
  renderer.render(scene, camera);
  if (!window.splatcli.ready) {
    if (mesh && sceneDrawn()) {
      window.splatcli.firstFrameMs = performance.now();
      window.splatcli.ready = true;
    }
  }
  if (!window.splatcli.ready) { queued = true; requestAnimationFrame(drawFrame); } // until the scene first shows
}

async function main() {
  state = await (await fetch("api/scene", { cache: "no-store" })).json();
  window.splatcli.marks.facts = performance.now();
  window.splatcli.version = state.version;
  scene.background = new THREE.Color().setRGB(...state.background, THREE.SRGBColorSpace);
  const r = state.radius || 1;
  camera.near = state.near; // splatcli render's near plane: the same Gaussians are drawn
  camera.far = 1000 * r;
  fillCameras();
  showFacts();
  const want = params.get("camera");
  const c = want && state.cameras.find((x) => x.name === want);
  if (want && !c) fail(`no camera named ${want}`);
  if (c) { useCamera(c); $("cams").value = c.name; } else resetView();
  $("reset").onclick = resetView;
  $("mode").onchange = (e) => setMode(e.target.value);
  $("show").hidden = !!state.static;
  addEventListener("resize", () => { renderer.setSize(innerWidth, innerHeight); setProjection(); });
  if (state.num_gaussians > 0) await loadSplats(state.version); // else training has not stepped yet: poll
  if (!state.static) setTimeout(poll, 2000);
}

main().catch(fail);
