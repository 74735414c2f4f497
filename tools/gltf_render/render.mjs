// Render flakedb's exported glTF spheres with three.js (WebGL 2) in headless Chromium.
//
//   node render.mjs JOB.json
//
// JOB.json: {"node_modules": DIR (with three and playwright-core), "chromium": PATH, "user_data_dir": DIR,
//            "renders": [{"glb": PATH, "out": PATH.f32, "size": N, "extent": E,
//                         "sun": {"direction": [x, y, z], "irradiance": E} | null,
//                         "environment": L | null}]}
// Each render: the .glb's scene alone, an orthographic camera on +z looking down -z covering
// [-extent, extent]^2, one DirectionalLight of intensity `irradiance` towards `direction` (three.js:
// a white Lambertian plane facing it has radiance irradiance / pi), and/or a uniform environment of
// radiance L (a constant float equirect map, prefiltered by three.js's PMREM), no tone mapping,
// linear sRGB, no antialiasing (one sample at each pixel centre), drawn into a float32 RGBA render
// target and read back as float32.  Writes OUT (size*size*3 float32, row 0 at the top) and prints
// one JSON line {"three": REVISION, "renderer": GL renderer string, "outputs": [...]}.
import { readFileSync, writeFileSync } from 'node:fs';
import { join, resolve } from 'node:path';
import { pathToFileURL } from 'node:url';

const job = JSON.parse(readFileSync(process.argv[2], 'utf8'));
const nm = resolve(job.node_modules);
const { chromium } = await import(pathToFileURL(join(nm, 'playwright-core', 'index.mjs')).href);

const ORIGIN = 'http://flakedb.invalid';
const PAGE = `<!doctype html><html><body>
<script type="importmap">{"imports": {"three": "${ORIGIN}/three/build/three.module.js",
                                      "three/addons/": "${ORIGIN}/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
window.renderOne = async (r) => {
  const renderer = new THREE.WebGLRenderer({ antialias: false, alpha: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(r.size, r.size, false);
  renderer.toneMapping = THREE.NoToneMapping;
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  const gl = renderer.getContext();
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0, 0, 0);
  const gltf = await new GLTFLoader().loadAsync(r.url);
  scene.add(gltf.scene);
  if (r.sun) {
    const light = new THREE.DirectionalLight(0xffffff, r.sun.irradiance);
    light.position.set(...r.sun.direction);
    light.target.position.set(0, 0, 0);
    scene.add(light, light.target);
  }
  if (r.environment !== null && r.environment !== undefined) {
    const w = 64, h = 32, L = r.environment;
    const data = new Float32Array(w * h * 4);
    for (let i = 0; i < w * h; i++) data.set([L, L, L, 1], 4 * i);
    const tex = new THREE.DataTexture(data, w, h, THREE.RGBAFormat, THREE.FloatType);
    tex.mapping = THREE.EquirectangularReflectionMapping;
    tex.colorSpace = THREE.LinearSRGBColorSpace;
    tex.needsUpdate = true;
    const pmrem = new THREE.PMREMGenerator(renderer);
    scene.environment = pmrem.fromEquirectangular(tex).texture;
  }
  const e = r.extent;
  const cam = new THREE.OrthographicCamera(-e, e, e, -e, 0.1, 10);
  cam.position.set(0, 0, 4);
  cam.lookAt(0, 0, 0);
  const rt = new THREE.WebGLRenderTarget(r.size, r.size, { type: THREE.FloatType, format: THREE.RGBAFormat,
    colorSpace: THREE.LinearSRGBColorSpace, depthBuffer: true, samples: 0,
    minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter });
  renderer.setRenderTarget(rt);
  renderer.render(scene, cam);
  const px = new Float32Array(r.size * r.size * 4);
  renderer.readRenderTargetPixels(rt, 0, 0, r.size, r.size, px);
  renderer.setRenderTarget(null);
  const rgb = new Float32Array(r.size * r.size * 3);
  for (let row = 0; row < r.size; row++) {          // WebGL's row 0 is the bottom: flip
    const src = (r.size - 1 - row) * r.size, dst = row * r.size;
    for (let c = 0; c < r.size; c++) for (let k = 0; k < 3; k++) rgb[3 * (dst + c) + k] = px[4 * (src + c) + k];
  }
  const dbg = gl.getExtension('WEBGL_debug_renderer_info');
  const info = { three: THREE.REVISION, webgl2: renderer.capabilities.isWebGL2 !== false,
                 renderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER) };
  renderer.dispose();
  const bytes = new Uint8Array(rgb.buffer);
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return { info, b64: btoa(s) };
};
window.ready = true;
</script></body></html>`;

const context = await chromium.launchPersistentContext(job.user_data_dir, {   // a fresh profile
  executablePath: job.chromium, headless: true,
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
         '--disable-background-networking', '--disable-component-update', '--disable-sync', '--no-first-run'],
});
const files = new Map();
try {
  const page = await context.newPage();
  const errors = [];
  page.on('pageerror', (e) => errors.push(String(e)));
  page.on('console', (m) => { if (m.type() === 'error') errors.push(m.text()); });
  await page.route(`${ORIGIN}/**`, async (route) => {
    const p = new URL(route.request().url()).pathname;
    let body, type = 'application/octet-stream';
    if (p === '/index.html') { body = PAGE; type = 'text/html'; }
    else if (p.startsWith('/three/')) { body = readFileSync(join(nm, p)); type = 'text/javascript'; }
    else if (files.has(p)) body = readFileSync(files.get(p));
    else return route.fulfill({ status: 404, body: 'not found' });
    return route.fulfill({ status: 200, contentType: type, body });
  });
  await page.goto(`${ORIGIN}/index.html`);
  await page.waitForFunction(() => window.ready === true, null, { timeout: 60000 }).catch(() => {
    throw new Error(`the page did not load three.js: ${errors.join('; ')}`);
  });
  const outputs = [];
  let info = null;
  for (const [i, r] of job.renders.entries()) {
    const key = `/file${i}.glb`;
    files.set(key, r.glb);
    const res = await page.evaluate((a) => window.renderOne(a), { url: ORIGIN + key, size: r.size, extent: r.extent,
      sun: r.sun ?? null, environment: r.environment ?? null }).catch((e) => {
      throw new Error(`render ${i} (${r.glb}) failed: ${e}; page errors: ${errors.join('; ')}`);
    });
    writeFileSync(r.out, Buffer.from(res.b64, 'base64'));
    info = res.info;
    outputs.push(r.out);
  }
  console.log(JSON.stringify({ ...info, chromium: await page.evaluate(() => navigator.userAgent), outputs, page_errors: errors }));
} finally {
  await context.close();
}
