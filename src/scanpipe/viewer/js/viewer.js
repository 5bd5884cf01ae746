// scanpipe's 3-D viewer: one textured glTF model, turned with the mouse, offline.
//
// Bundled with three.js into ../assets/viewer.bundle.js by `npm run build` (see build.sh);
// the bundle exposes window.ScanpipeViewer.start(options). The page tells its state in
// document.body.dataset.viewer ("loading", "ready", "error") and, once a frame is drawn, in
// window.scanpipeViewerInfo, so a headless browser test can wait for it.
import {
  BackSide, Box3, Color, DirectionalLight, FrontSide, HemisphereLight, PerspectiveCamera, Scene,
  SRGBColorSpace, Vector3, WebGLRenderer,
} from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { DRACOLoader } from "three/examples/jsm/loaders/DRACOLoader.js";
// The Draco decoder (a GLB written with --draco) is bundled, not fetched: the page works offline
// and from file://.
import dracoWrapper from "three/examples/jsm/libs/draco/gltf/draco_wasm_wrapper.js" with { type: "text" };
import dracoWasm from "three/examples/jsm/libs/draco/gltf/draco_decoder.wasm" with { type: "bytes" };
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

function setState(state, message) {
  document.body.dataset.viewer = state;
  const status = document.getElementById("scanpipe-viewer-status");
  if (status) status.textContent = message || "";
}

function base64ToBuffer(text) {
  const binary = atob(text.replace(/\s+/g, ""));
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes.buffer;
}

async function modelBytes(options) {
  if (options.glbElementId) {
    const element = document.getElementById(options.glbElementId);
    if (!element || !element.textContent.trim()) throw new Error("the page holds no model");
    return base64ToBuffer(element.textContent);
  }
  const response = await fetch(options.glbUrl);
  if (!response.ok) throw new Error(`${options.glbUrl}: HTTP ${response.status}`);
  return response.arrayBuffer();
}

// A scan is seen from inside: its faces look towards the scanner at the origin. Drawing only the
// side that faces the scanner lets the outside view look into the rooms ("dollhouse") instead of
// at the backs of the walls. Which side that is is read off a sample of the triangles.
function facesTowardOrigin(mesh) {
  const position = mesh.geometry.attributes.position, index = mesh.geometry.index;
  const count = Math.floor((index ? index.count : position.count) / 3);
  const step = Math.max(1, Math.floor(count / 20000));
  const a = new Vector3(), b = new Vector3(), c = new Vector3(), n = new Vector3();
  let toward = 0, away = 0;
  for (let t = 0; t < count; t += step) {
    const i = index ? index.getX(3 * t) : 3 * t;
    const j = index ? index.getX(3 * t + 1) : 3 * t + 1;
    const k = index ? index.getX(3 * t + 2) : 3 * t + 2;
    a.fromBufferAttribute(position, i).applyMatrix4(mesh.matrixWorld);
    b.fromBufferAttribute(position, j).applyMatrix4(mesh.matrixWorld);
    c.fromBufferAttribute(position, k).applyMatrix4(mesh.matrixWorld);
    n.subVectors(b, a).cross(c.sub(a));
    if (n.dot(a) < 0) toward++; else away++;
  }
  return toward >= away;
}

function faceTheScanner(root) {
  root.updateMatrixWorld(true);
  root.traverse((node) => {
    if (!node.isMesh) return;
    const side = facesTowardOrigin(node) ? FrontSide : BackSide;
    const materials = Array.isArray(node.material) ? node.material : [node.material];
    for (const material of materials) { material.side = side; material.needsUpdate = true; }
  });
}

function countGeometry(root) {
  let triangles = 0, vertices = 0, textured = false;
  root.traverse((node) => {
    if (!node.isMesh) return;
    const geometry = node.geometry;
    const count = geometry.index ? geometry.index.count : geometry.attributes.position.count;
    triangles += Math.floor(count / 3);
    vertices += geometry.attributes.position.count;
    const materials = Array.isArray(node.material) ? node.material : [node.material];
    if (materials.some((m) => m && m.map)) textured = true;
  });
  return { triangles, vertices, textured };
}

/** DRACOLoader with its decoder from the bundle instead of a decoder path. */
class EmbeddedDracoLoader extends DRACOLoader {
  _loadLibrary(url, responseType) {
    return Promise.resolve(responseType === "arraybuffer" ? dracoWasm.slice().buffer : dracoWrapper);
  }
}

async function start(options) {
  setState("loading", "Loading the model…");
  const canvas = document.getElementById(options.canvasId);
  const renderer = new WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.outputColorSpace = SRGBColorSpace;
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  const scene = new Scene();
  scene.background = new Color(0xf4f4f4);
  scene.add(new HemisphereLight(0xffffff, 0x888888, 2.5));
  const sun = new DirectionalLight(0xffffff, 1.0);
  sun.position.set(1, 2, 1.5);
  scene.add(sun);

  const gltf = await new GLTFLoader().setDRACOLoader(new EmbeddedDracoLoader())
    .parseAsync(await modelBytes(options), "");
  const model = gltf.scene;
  scene.add(model);
  const info = countGeometry(model);
  if (info.triangles === 0) throw new Error("the model has no triangles");
  faceTheScanner(model);

  const box = new Box3().setFromObject(model);
  const centre = box.getCenter(new Vector3());
  const size = box.getSize(new Vector3());
  const radius = Math.max(size.length() / 2, 1e-3);
  const camera = new PerspectiveCamera(50, 1, radius / 1000, radius * 20);
  const controls = new OrbitControls(camera, canvas);
  // The scanner stood at the model's origin: the "inside" view looks from there.
  const views = {
    outside: () => {
      camera.fov = 50;
      camera.position.copy(centre).add(new Vector3(0.9, 1.1, 1.3).multiplyScalar(radius * 1.4));
      controls.target.copy(centre);
    },
    inside: () => {
      camera.fov = 80;
      camera.position.set(0, 0, 0);
      controls.target.set(0, 0, -radius * 0.05);
    },
  };

  function resize() {
    const width = canvas.clientWidth || 640, height = canvas.clientHeight || 480;
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
  }
  function draw() {
    resize();
    controls.update();
    renderer.render(scene, camera);
  }
  controls.addEventListener("change", () => renderer.render(scene, camera));
  window.addEventListener("resize", draw);
  for (const [name, apply] of Object.entries(views)) {
    const button = document.getElementById(`scanpipe-view-${name}`);
    if (button) button.addEventListener("click", () => { apply(); draw(); });
  }
  views.outside();
  draw();
  window.scanpipeViewerInfo = { ...info, radius, min: box.min.toArray(), max: box.max.toArray() };
  setState("ready", `${info.triangles.toLocaleString("en")} triangles` +
    (info.textured ? ", textured" : ", untextured") + " · drag to turn, scroll to zoom");
}

window.ScanpipeViewer = {
  start: (options) => start(options).catch((error) => {
    setState("error", `The 3-D view could not be shown: ${error.message || error}`);
  }),
};
