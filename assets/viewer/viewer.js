// The report's 3D viewer: the inspection's mesh (GLB, with its vertex colours), orbit, zoom and
// reset. Bundled with three.js into one classic script (build.sh) that the report inlines: the
// page loads nothing from anywhere. Each `.viewer` element names its mesh either by URL
// (`data-glb-url`, same origin) or by the id of an element holding it in base64
// (`data-glb-element`). When the first frame is drawn it reads the frame back and sets
// `data-state` to `drawn` (some pixels differ from the background) or `blank`; `failed` with a
// message when the mesh cannot be shown. `data-frame-ms` is how long the first frame took to draw.
import {
  AmbientLight,
  Box3,
  Color,
  DirectionalLight,
  MeshStandardMaterial,
  PerspectiveCamera,
  Scene,
  Vector3,
  WebGLRenderer,
} from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';

const BACKGROUND = 0xf4f4f4;

function fromBase64(text) {
  const binary = atob(text.trim());
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes.buffer;
}

function meshBytes(container) {
  if (container.dataset.glbUrl) {
    return fetch(container.dataset.glbUrl).then((r) => {
      if (!r.ok) throw new Error('the mesh answered HTTP ' + r.status);
      return r.arrayBuffer();
    });
  }
  const holder = document.getElementById(container.dataset.glbElement || '');
  if (!holder) return Promise.reject(new Error('no mesh in the page'));
  return Promise.resolve(fromBase64(holder.textContent));
}

function start(container) {
  const status = container.querySelector('.viewer-status');
  const say = (text) => { if (status) status.textContent = text; };
  const width = Math.max(320, container.clientWidth || 800);
  const height = Math.round(width * 0.55);
  let renderer;
  try {
    renderer = new WebGLRenderer({ antialias: true });
  } catch (e) {
    container.dataset.state = 'failed';
    say('The 3D view needs WebGL, which this browser does not offer.');
    return;
  }
  renderer.setPixelRatio(1);
  renderer.setSize(width, height);
  container.appendChild(renderer.domElement);
  const scene = new Scene();
  scene.background = new Color(BACKGROUND);
  scene.add(new AmbientLight(0xffffff, 0.9));
  const camera = new PerspectiveCamera(35, width / height, 1e-4, 10);
  const light = new DirectionalLight(0xffffff, 1.8);
  camera.add(light);
  scene.add(camera);
  const controls = new OrbitControls(camera, renderer.domElement);
  let home = null;
  const render = () => renderer.render(scene, camera);
  controls.addEventListener('change', render);
  const reset = () => {
    if (!home) return;
    camera.position.copy(home.position);
    controls.target.copy(home.target);
    camera.near = home.near;
    camera.far = home.far;
    camera.updateProjectionMatrix();
    controls.update();
    render();
  };
  const button = container.querySelector('.viewer-reset');
  if (button) button.addEventListener('click', reset);
  say('Loading the mesh…');
  meshBytes(container)
    .then((bytes) => new Promise((resolve, reject) => new GLTFLoader().parse(bytes, '', resolve, reject)))
    .then((gltf) => {
      let triangles = 0;
      gltf.scene.traverse((node) => {
        if (!node.isMesh) return;
        // The GLB carries positions and colours only: normals for the light, a matte material.
        node.geometry.computeVertexNormals();
        node.material = new MeshStandardMaterial({ vertexColors: true, metalness: 0.05, roughness: 0.75 });
        triangles += node.geometry.index ? node.geometry.index.count / 3 : node.geometry.attributes.position.count / 3;
      });
      scene.add(gltf.scene);
      const box = new Box3().setFromObject(gltf.scene);
      const size = box.getSize(new Vector3()).length();
      const centre = box.getCenter(new Vector3());
      home = {
        position: centre.clone().add(new Vector3(0.55, 0.35, 0.75).multiplyScalar(1.6 * size)),
        target: centre,
        near: size / 1000,
        far: size * 10,
      };
      // The first frame, timed to the end of its drawing (gl.finish), for the docs' figures.
      const gl = renderer.getContext();
      const started = performance.now();
      reset();
      gl.finish();
      container.dataset.frameMs = (performance.now() - started).toFixed(1);
      // Read the first frame back: a viewer that drew nothing says so.
      const pixels = new Uint8Array(width * height * 4);
      gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
      const bg = new Color(BACKGROUND);
      const [r, g, b] = [bg.r, bg.g, bg.b].map((c) => Math.round(c * 255));
      let differing = 0;
      for (let i = 0; i < pixels.length; i += 4) {
        if (Math.abs(pixels[i] - r) + Math.abs(pixels[i + 1] - g) + Math.abs(pixels[i + 2] - b) > 12) differing++;
      }
      container.dataset.state = differing > 0.01 * width * height ? 'drawn' : 'blank';
      container.dataset.triangles = String(triangles);
      say(`${triangles.toLocaleString('en')} triangles. Drag to orbit, scroll to zoom, right-drag to pan.`);
    })
    .catch((e) => {
      container.dataset.state = 'failed';
      say('The 3D view could not be shown: ' + e.message);
      console.error(e);
    });
}

document.querySelectorAll('.viewer').forEach(start);
