// omnisplat viewer page: GaussianSplats3D (three.js) on the scene's gaussians.ply, or with ?format=spz on its
// gaussians.spz (a fifth of the bytes, for slow links; parsing it takes longer).
//
// Camera: OpenCV camera-to-world c2w (x right, y down, z forward), row-major 16 numbers, from the query
// (?c2w=...&fov_deg=...&width=...&height=...) or reference A's pose; three.js camera world matrix =
// c2w @ diag(1, -1, -1, 1). SPZ holds the scene in a RUB world (the scene's OpenCV world turned by
// diag(1, -1, -1)): there the camera's world matrix is diag(1, -1, -1, 1) @ c2w @ diag(1, -1, -1, 1).
// fov_deg is horizontal (as the render API); three.js takes a vertical one.
// Background black: the canvas is the plain front-to-back composite over black, as the render API's
// default (compositing=plain). For tests: window.viewerReady, window.viewerInfo.
import * as THREE from 'three';
import * as GaussianSplats3D from '@mkkellogg/gaussian-splats-3d';

const config = JSON.parse(document.getElementById('omnisplat-config').textContent);
const query = new URLSearchParams(window.location.search);
const status = document.getElementById('status');
const SPZ = query.get('format') === 'spz'; // the route refuses any other value than ply and spz
const LOADER_PROCESSING = 1; // GaussianSplats3D's LoaderStatus.Processing (not exported by the module)
window.viewerReady = false;
window.viewerInfo = { splatCount: null, error: null, loadSeconds: null, downloadPercent: null };

function fail(message) {
  window.viewerInfo.error = String(message);
  status.textContent = 'error: ' + message;
  document.body.classList.remove('bare'); // bare=1 hides the panel: an error shows it
  console.error('omnisplat viewer: ' + message);
}

function parseC2w(text) {
  const v = text.split(',').map(Number);
  if ((v.length !== 16 && v.length !== 12) || v.some((x) => !Number.isFinite(x))) {
    throw new Error('c2w: expected 16 or 12 comma-separated numbers');
  }
  if (v.length === 12) v.push(0, 0, 0, 1);
  return v;
}

function positiveNumber(name, fallback) {
  if (!query.has(name)) return fallback;
  const x = Number(query.get(name));
  if (!(x > 0) || !Number.isFinite(x)) throw new Error(`${name}: expected a positive number`);
  return x;
}

function verticalFov(hfovDeg, aspect) {
  return 2 * Math.atan(Math.tan((hfovDeg * Math.PI) / 360) / aspect) * 180 / Math.PI;
}

const frame = () => new Promise((resolve) => requestAnimationFrame(() => resolve()));

// OpenCV c2w (row-major 16) -> three.js camera position, up, rotation and orbit centre (1 unit ahead):
// world matrix = c2w @ diag(1, -1, -1, 1), turned into SPZ's world when the page shows the SPZ.
function cameraPose(c2w) {
  const m = new THREE.Matrix4().fromArray(c2w).transpose(); // fromArray is column-major
  if (SPZ) m.premultiply(new THREE.Matrix4().makeScale(1, -1, -1));
  m.multiply(new THREE.Matrix4().makeScale(1, -1, -1));
  const position = new THREE.Vector3().setFromMatrixPosition(m);
  const up = new THREE.Vector3().setFromMatrixColumn(m, 1).normalize();
  const forward = new THREE.Vector3().setFromMatrixColumn(m, 2).negate().normalize();
  const quaternion = new THREE.Quaternion().setFromRotationMatrix(new THREE.Matrix4().extractRotation(m));
  return { position, up, quaternion, target: position.clone().addScaledVector(forward, 1.0) };
}

// Resolves once the splats are sorted for the current camera and drawn since.
async function settled(viewer) {
  await frame();
  while (!viewer.splatRenderReady || viewer.sortRunning) await frame();
  await frame();
  while (viewer.sortRunning) await frame();
  viewer.forceRenderNextFrame(); // draw with the finished sort
  await frame();
  await frame();
}

async function main() {
  const c2w = query.has('c2w') ? parseC2w(query.get('c2w')) : (config.c2w || [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]);
  const fovDeg = positiveNumber('fov_deg', config.fov_deg || 90);
  const root = document.getElementById('view');
  if (query.has('width') || query.has('height')) {
    root.style.width = positiveNumber('width', 640) + 'px';
    root.style.height = positiveNumber('height', 480) + 'px';
  }
  if (query.get('bare') === '1') document.body.classList.add('bare');
  const size = () => [Math.max(1, root.clientWidth), Math.max(1, root.clientHeight)];

  const pose = cameraPose(c2w);
  const [w, h] = size();
  const camera = new THREE.PerspectiveCamera(verticalFov(fovDeg, w / h), w / h, 0.01, 1000);
  camera.position.copy(pose.position);
  camera.up.copy(pose.up);
  camera.quaternion.copy(pose.quaternion);

  const viewer = new GaussianSplats3D.Viewer({
    rootElement: root,
    camera,
    cameraUp: pose.up.toArray(),
    initialCameraPosition: pose.position.toArray(),
    initialCameraLookAt: pose.target.toArray(),
    useBuiltInControls: true,
    selfDrivenMode: true,
    ignoreDevicePixelRatio: true,
    sphericalHarmonicsDegree: 1, // the encoder fits degree-1 colour (rasterizer.view_colour)
    antialiased: false,
    // software GL (SwiftShader) draws a black frame with the GPU distance pre-pass
    gpuAcceleratedSort: false,
    // needs cross-origin isolation (the service sends COOP/COEP); copy messages otherwise
    sharedMemoryForWorkers: Boolean(window.crossOriginIsolated),
    // 0.4.7 drops the last splat when it reorders the data (updateDataTexturesFromBaseData)
    optimizeSplatData: false,
    sceneRevealMode: GaussianSplats3D.SceneRevealMode.Instant,
    // Instant reveal still steps a "visible region changing" flag at 0.003 a frame, which redraws every
    // frame for ~1500 frames; this makes that step complete in one frame (the image is not faded anyway)
    sceneFadeInRateMultiplier: 400,
    // draw when the camera or the sort changes, not every frame (software GL takes seconds a frame)
    renderMode: GaussianSplats3D.RenderMode.OnChange,
    logLevel: GaussianSplats3D.LogLevel.None,
  });
  window.viewer = viewer;
  for (const controls of [viewer.perspectiveControls, viewer.controls]) {
    if (!controls) continue;
    controls.minPolarAngle = 0; // any starting pitch
    controls.maxPolarAngle = Math.PI;
    controls.target.copy(pose.target);
    controls.update();
  }

  new ResizeObserver(() => {
    const [rw, rh] = size();
    camera.aspect = rw / rh;
    camera.fov = verticalFov(fovDeg, rw / rh);
    camera.updateProjectionMatrix();
    viewer.forceRenderNextFrame();
  }).observe(root);

  // with renderMode OnChange, draw once more when a sort lands after the camera stopped
  let wasSorting = false;
  const watchSort = () => {
    if (wasSorting && !viewer.sortRunning) viewer.forceRenderNextFrame();
    wasSorting = viewer.sortRunning;
    requestAnimationFrame(watchSort);
  };
  requestAnimationFrame(watchSort);

  // fly: W/S forward/back, A/D left/right, Q/E down/up (camera and orbit centre move together)
  window.addEventListener('keydown', (event) => {
    const step = event.shiftKey ? 0.5 : 0.1;
    const dir = new THREE.Vector3();
    const fwd = new THREE.Vector3();
    camera.getWorldDirection(fwd);
    const right = new THREE.Vector3().crossVectors(fwd, camera.up).normalize();
    switch (event.code) {
      case 'KeyW': dir.copy(fwd); break;
      case 'KeyS': dir.copy(fwd).negate(); break;
      case 'KeyD': dir.copy(right); break;
      case 'KeyA': dir.copy(right).negate(); break;
      case 'KeyE': dir.copy(camera.up); break;
      case 'KeyQ': dir.copy(camera.up).negate(); break;
      default: return;
    }
    dir.multiplyScalar(step);
    camera.position.add(dir);
    if (viewer.controls) viewer.controls.target.add(dir);
  });

  const t0 = performance.now();
  const file = SPZ ? 'gaussians.spz' : 'gaussians.ply';
  // addSplatScene answers an AbortablePromise whose then() takes no rejection handler, so awaiting it directly never
  // ends when the download fails (the scene deleted, the key's cookie gone); its catch() passes the failure on
  const loading = viewer.addSplatScene(SPZ ? config.spz : config.ply, {
    format: SPZ ? GaussianSplats3D.SceneFormat.Spz : GaussianSplats3D.SceneFormat.Ply,
    showLoadingUI: false,
    progressiveLoad: false,
    // a scene's PLY is tens of MB: the panel says how far its download and parsing have come
    onProgress: (percent, label, stage) => {
      if (stage === LOADER_PROCESSING) {
        status.textContent = 'building the splats\u2026';
      } else {
        window.viewerInfo.downloadPercent = percent;
        status.textContent = Number.isFinite(percent) ? `downloading ${file}: ${Math.round(percent)}%`
          : `downloading ${file}\u2026`; // no Content-Length: no share to show
      }
    },
  });
  await new Promise((resolve, reject) => loading.then(resolve).catch(reject));
  viewer.start();
  window.viewerInfo.loadedSeconds = (performance.now() - t0) / 1000;
  await settled(viewer); // ready = loaded, sorted for this camera, and drawn since
  const count = viewer.getSplatMesh().getSplatCount();
  window.viewerInfo.splatCount = count;
  window.viewerInfo.loadSeconds = (performance.now() - t0) / 1000;
  status.textContent = `${count} splats loaded in ${window.viewerInfo.loadSeconds.toFixed(1)} s`;
  window.viewerReady = true;

  // Place the camera at another OpenCV c2w (16 numbers) without reloading; resolves once drawn.
  window.setCameraC2w = async (values) => {
    const next = cameraPose(parseC2w(values.join(',')));
    camera.up.copy(next.up);
    camera.position.copy(next.position);
    camera.quaternion.copy(next.quaternion);
    camera.updateMatrixWorld(true);
    if (viewer.controls) {
      viewer.controls.target.copy(next.target);
      viewer.controls.update();
    }
    await settled(viewer);
    return true;
  };
}

main().catch((err) => fail(err && err.message ? err.message : err));
