// prt-three.js: a scene written by prt-web (prt.export.web) as three.js meshes, for any three.js app
// (docs/guides/three.md).  One ES module; it imports "three" (the app's import map names it; the
// folder ships three.js 0.185.1 in vendor/three/) and reads web.json and the files beside it.
//
//   const prt = await loadPRT("scene/");        // a folder written by prt-web
//   scene.add(prt.object);                      // a THREE.Group: one mesh, the scene's triangles
//   prt.setEnvmap("studio"); prt.rotation = 30; prt.exposure = 1.5;   // or prt.setLightProbe(probe)
//
// The material is a THREE.ShaderMaterial whose fragment stage is the page's G-buffer, transfer and
// shade passes in one (shaders/three.frag, assembled by prt.export.web_assets from the runtime's own
// shader files and the scene's generated network GLSL, with its weight texture): per fragment, the
// segment's network gives the transfer vector (16 SH coefficients; 64 with interreflection) and the
// SH light shades it, diffuse or Phong glossy through the Gaunt light matrices.  It writes linear
// radiance and includes three's tone mapping and output colour space, so that it sits in a
// three.js scene like three's own materials (usePRTToneMapping gives the page's tone curve).
// Forward shading runs the networks for every fragment drawn, every frame: render on demand.

import * as THREE from "three";

export const WEB_FORMAT = "prt-web";
export const WEB_VERSION = 1;
export const THREE_REVISIONS = [185, 185];  // the three.js revisions this module is tested with (vendor/three/VERSION.json)

export class PRTError extends Error {}

// ------------------------------------------------------------------ files

async function fetchOk(url, name) {
  let response;
  try {
    response = await fetch(new URL(name, url), { cache: "no-cache" });
  } catch (err) {
    throw new PRTError(`${name}: cannot be fetched (${err.message})`);
  }
  if (!response.ok) throw new PRTError(`${name}: HTTP ${response.status} ${response.statusText || ""}(missing file?)`.replace("  ", " "));
  return response;
}

async function fetchBytes(url, web, name) {
  const data = await (await fetchOk(url, name)).arrayBuffer();
  const expected = web.files[name];
  if (expected !== undefined && data.byteLength !== expected) {
    throw new PRTError(`${name}: ${data.byteLength} bytes, web.json says ${expected} (a corrupt or truncated file)`);
  }
  return data;
}

async function fetchText(url, web, name) {
  const text = await (await fetchOk(url, name)).text();
  if (web.files[name] !== undefined && new TextEncoder().encode(text).length !== web.files[name]) {
    throw new PRTError(`${name}: not the file web.json lists (a corrupt or changed file)`);
  }
  return text;
}

async function fetchWeb(url) {
  const text = await (await fetchOk(url, "web.json")).text();
  let web;
  try {
    web = JSON.parse(text);
  } catch (err) {
    throw new PRTError(`web.json: not valid JSON (${err.message})`);
  }
  if (!web || typeof web !== "object" || web.format !== WEB_FORMAT) throw new PRTError(`web.json: not a prt-web file (format ${JSON.stringify(web && web.format)})`);
  if (!Number.isInteger(web.version) || web.version > WEB_VERSION) {
    throw new PRTError(`web.json: format version ${web.version} is newer than this module reads (${WEB_VERSION}); write the folder again with the prt-web that wrote web.json`);
  }
  for (const key of ["scene", "camera", "geometry", "transfer", "uniforms", "lighting", "material", "files", "three"]) {
    if (!(key in web)) throw new PRTError(`web.json: no "${key}" (a corrupt file, or one written by a prt-web without three.js support)`);
  }
  if (web.deformation) throw new PRTError("web.json: a deformable scene; prt-three.js draws rigid scenes (index.html plays the recorded poses)");
  if (!web.three.programs["three.frag"]) throw new PRTError("web.json: no three.js programs (a corrupt file)");
  return web;
}

// ------------------------------------------------------------------ SH light (twins of prt-web.js's)

// SH rotation about +Y by theta: D = C0 + sum_k Ck cos(k theta) + Sk sin(k theta) (web_assets.rotation_fourier).
function shRotationY(fourier, theta) {
  const n = fourier[0].length;
  const d = fourier[0].map((row) => row.slice());
  for (let k = 1; 2 * k < fourier.length; ++k) {
    const c = Math.cos(k * theta), s = Math.sin(k * theta);
    for (let i = 0; i < n; ++i) for (let j = 0; j < n; ++j) d[i][j] += fourier[2 * k - 1][i][j] * c + fourier[2 * k][i][j] * s;
  }
  return d;
}

// Real SH of 4 bands at unit direction (x, y, z): runtime/sh.py's basis (shaders/sh_basis.glsl).
export function shBasis(x, y, z) {
  const x2 = x * x, y2 = y * y, z2 = z * z;
  return [
    0.28209479177387814, 0.4886025119029199 * y, 0.4886025119029199 * z, 0.4886025119029199 * x,
    1.0925484305920792 * x * y, 1.0925484305920792 * y * z, 0.31539156525252005 * (3 * z2 - 1), 1.0925484305920792 * x * z,
    0.5462742152960396 * (x2 - y2), 0.5900435899266435 * y * (3 * x2 - y2), 2.890611442640554 * x * y * z, 0.4570457994644658 * y * (5 * z2 - 1),
    0.3731763325901154 * z * (5 * z2 - 3), 0.4570457994644658 * x * (5 * z2 - 1), 1.445305721320277 * z * (x2 - y2), 0.5900435899266435 * x * (x2 - 3 * y2),
  ];
}

function solve(a, b) {  // a x = b (n x n, n x m), Gauss-Jordan with partial pivoting; float64
  const n = a.length, m = b[0].length;
  const A = a.map((row, i) => [...row, ...b[i]]);
  for (let c = 0; c < n; ++c) {
    let p = c;
    for (let r = c + 1; r < n; ++r) if (Math.abs(A[r][c]) > Math.abs(A[p][c])) p = r;
    [A[c], A[p]] = [A[p], A[c]];
    for (let r = 0; r < n; ++r) {
      if (r === c) continue;
      const f = A[r][c] / A[c][c];
      for (let k = c; k < n + m; ++k) A[r][k] -= f * A[c][k];
    }
  }
  return A.map((row, i) => row.slice(n).map((v) => v / A[i][i]));
}

let fitDirections = null;  // fixed directions and the least-squares projection onto the 16 SH (16 x N)
function shFit() {
  if (fitDirections) return fitDirections;
  const dirs = [];
  const count = 64;
  for (let i = 0; i < count; ++i) {  // a Fibonacci sphere: the basis is well conditioned on it
    const y = 1 - (2 * (i + 0.5)) / count, r = Math.sqrt(1 - y * y), phi = i * Math.PI * (3 - Math.sqrt(5));
    dirs.push([r * Math.cos(phi), y, r * Math.sin(phi)]);
  }
  const B = dirs.map((d) => shBasis(...d));  // N x 16
  const BtB = Array.from({ length: 16 }, (_, i) => Array.from({ length: 16 }, (_, j) => B.reduce((s, row) => s + row[i] * row[j], 0)));
  const Bt = Array.from({ length: 16 }, (_, i) => B.map((row) => row[i]));
  fitDirections = { dirs, project: solve(BtB, Bt) };
  return fitDirections;
}

// The SH coefficients of g(w) = f(M w) from those of f: g = D f, D (16 x 16) for a rotation M
// (3 x 3 rows).  Exact for 4 bands (a rotation keeps each band; the fit is least squares on 64
// directions, 16 unknowns).  The light in an object's frame is D(R) L for its world rotation R.
export function shRotation(m) {
  const { dirs, project } = shFit();
  const Y = dirs.map(([x, y, z]) => shBasis(m[0][0] * x + m[0][1] * y + m[0][2] * z, m[1][0] * x + m[1][1] * y + m[1][2] * z,
    m[2][0] * x + m[2][1] * y + m[2][2] * z));  // N x 16
  return project.map((row) => Array.from({ length: 16 }, (_, j) => row.reduce((s, v, k) => s + v * Y[k][j], 0)));
}

const applyRows = (d, light) => d.map((row) => [0, 1, 2].map((c) => row.reduce((s, v, j) => s + v * light[j][c], 0)));

function exponentKey(e) {  // Python's repr of a float, as web_assets._key writes the lobes' keys
  return Number.isInteger(e) ? `${e}.0` : String(e);
}

// The uniforms of shading.glsl (prt.runtime.shading.shader_uniforms) from the light (16 x 3).
function shadingUniforms(web, light, material, out) {
  const n = light.length;
  const m = [0, 1, 2].map(() => Array.from({ length: n }, () => new Float64Array(n)));
  for (const [i, j, k, g] of web.lighting.gaunt) for (let c = 0; c < 3; ++c) m[c][k][j] += light[i][c] * g;
  const matrix = out.u_light_matrix.value;
  for (let c = 0; c < 3; ++c) for (let bi = 0; bi < 4; ++bi) for (let bj = 0; bj < 4; ++bj) {
    const b = 16 * c + 4 * bi + bj;
    for (let col = 0; col < 4; ++col) for (let row = 0; row < 4; ++row) matrix[b * 16 + col * 4 + row] = m[c][4 * bi + row][4 * bj + col];
  }
  const lobe = web.material.lobes[exponentKey(material.exponent)];
  if (!lobe) throw new PRTError(`web.json: no Phong lobe for exponent ${material.exponent}`);
  out.u_light.value.set(light.flat());
  out.u_lobe.value.set(lobe);
  out.u_albedo.value.set(material.albedo);
  out.u_specular.value.set(material.specular);
  out.u_material_kind.value = web.material.kinds.indexOf(material.kind);
}

function decodeRGBE(bytes, width, height) {  // byte * 2^(e - 136); rows flipped: three's equirect v = 1 is +Y
  const out = new Float32Array(width * height * 4);
  for (let row = 0; row < height; ++row) {
    for (let x = 0; x < width; ++x) {
      const i = row * width + x, o = (height - 1 - row) * width + x;
      const e = bytes[4 * i + 3];
      const f = e ? Math.pow(2, e - 136) : 0;
      out[4 * o] = bytes[4 * i] * f;
      out[4 * o + 1] = bytes[4 * i + 1] * f;
      out[4 * o + 2] = bytes[4 * i + 2] * f;
      out[4 * o + 3] = 1;
    }
  }
  return out;
}

// ------------------------------------------------------------------ tone mapping

export const TONEMAP_MAX = 10000.0;  // prt.runtime.shading.TONEMAP_MAX (tests/test_three.py checks the two agree)
const PRT_TONE_CURVE = `vec3 CustomToneMapping( vec3 color ) {  // prt's tone curve (shaders/tonemap.glsl): ACES fit (Narkowicz 2015)
	color = clamp( color * toneMappingExposure, 0.0, ${TONEMAP_MAX.toFixed(1)} );
	return clamp( ( color * ( 2.51 * color + 0.03 ) ) / ( color * ( 2.43 * color + 0.59 ) + 0.14 ), 0.0, 1.0 );
}`;

// The page's tone curve for every material of this renderer: CustomToneMapping with prt's ACES fit
// (exposure is renderer.toneMappingExposure), sRGB output.  Optional: the prt material follows
// whatever tone mapping the renderer has; this makes its frame the page's (index.html's).
export function usePRTToneMapping(renderer) {
  const chunk = THREE.ShaderChunk.tonemapping_pars_fragment;
  const stock = "vec3 CustomToneMapping( vec3 color ) { return color; }";
  if (!chunk.includes("prt's tone curve")) {
    if (!chunk.includes(stock)) throw new PRTError(`three.js r${THREE.REVISION}: its tone-mapping chunk has no CustomToneMapping to replace (tested with r${THREE_REVISIONS[0]})`);
    THREE.ShaderChunk.tonemapping_pars_fragment = chunk.replace(stock, PRT_TONE_CURVE);
  }
  renderer.toneMapping = THREE.CustomToneMapping;
  renderer.outputColorSpace = THREE.SRGBColorSpace;
}

// ------------------------------------------------------------------ the scene

function dataTexture(data, width, height) {
  const t = new THREE.DataTexture(data, width, height, THREE.RGBAFormat, THREE.FloatType);
  t.minFilter = t.magFilter = THREE.NearestFilter;
  t.generateMipmaps = false;
  t.needsUpdate = true;
  return t;
}

const identity3 = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
const PREPASS_VERTEX = "invariant gl_Position;\nvoid main() { gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }";

// A built scene in three.js: `object` (a THREE.Group holding one mesh) to add to a THREE.Scene;
// the light (setEnvmap, setLightProbe, rotation in degrees about +Y, exposure) and the material
// (setMaterial) change uniforms only.
export class PRTScene {
  constructor(web, files, sources, options = {}) {
    this.web = web;
    this.envmaps = Object.keys(web.lighting.envmaps);
    this._envmap = web.lighting.default;
    this._probe = null;
    this._rotation = 0;
    this._material = "scene";
    this._exponent = web.material.glossy.exponent;
    this._frame = -1;
    this._backgrounds = new Map();
    this._files = files;
    const g = web.geometry, bytes = files[g.file];
    const section = (name, Type) => new Type(bytes.slice(g[name].offset, g[name].offset + g[name].bytes));
    const geometry = new THREE.BufferGeometry();
    const records = new THREE.InterleavedBuffer(section("records", Float32Array), 9);  // position, normal, face normal
    geometry.setAttribute("position", new THREE.InterleavedBufferAttribute(records, 3, 0));
    geometry.setAttribute("normal", new THREE.InterleavedBufferAttribute(records, 3, 3));
    geometry.setAttribute("prt_face_normal", new THREE.InterleavedBufferAttribute(records, 3, 6));
    const info = new THREE.BufferAttribute(section("info", Int32Array), 2);  // object id, two-sided (an integer attribute)
    info.gpuType = THREE.IntType;
    geometry.setAttribute("prt_info", info);
    if (g.albedo_uv) geometry.setAttribute("prt_albedo_uv", new THREE.BufferAttribute(section("albedo_uv", Float32Array), 2));
    // Closed faces with back-face culling, then the two-sided ones without (runtime/gbuffer.py).
    if (g.closed) geometry.addGroup(0, g.closed, 0);
    if (g.corners > g.closed) geometry.addGroup(g.closed, g.corners - g.closed, 1);
    geometry.computeBoundingSphere();
    geometry.computeBoundingBox();
    this.geometry = geometry;

    const u = web.uniforms;
    const uniforms = {
      prt_kd_nodes: { value: Float32Array.from(u.gbuffer.prt_kd_nodes.flat()) },
      prt_kd_roots: { value: Int32Array.from(u.gbuffer.prt_kd_roots) },
      prt_segment_min: { value: Float32Array.from(u.gbuffer.prt_segment_min.flat()) },
      prt_segment_max: { value: Float32Array.from(u.gbuffer.prt_segment_max.flat()) },
      u_analytic_scale: { value: Float32Array.from(u.transfer.u_analytic_scale.flat()) },
      u_eye: { value: new THREE.Vector3() },
      u_exposure: { value: 1 },
      u_light: { value: new Float32Array(48) },
      u_light_matrix: { value: new Float32Array(48 * 16) },
      u_lobe: { value: new Float32Array(16) },
      u_albedo: { value: new Float32Array(3) },
      u_specular: { value: new Float32Array(3) },
      u_material_kind: { value: 0 },
    };
    if (u.transfer.u_segment_net) {
      uniforms.u_segment_net = { value: Int32Array.from(u.transfer.u_segment_net) };
      uniforms.u_segment_base = { value: Int32Array.from(u.transfer.u_segment_base) };
    }
    if (web.weights) uniforms.prt_weights = { value: dataTexture(new Float32Array(files[web.weights.file]), web.weights.width, web.weights.height) };
    this.uniforms = uniforms;
    this.programs = { plain: this._materials(sources["three.vert"], sources["three.frag"]) };
    if (web.material.table) {
      const rows = web.material.table;  // (4, K, 4)
      uniforms.u_material_table = { value: dataTexture(Float32Array.from(rows.flat(2)), rows[0].length, rows.length) };
      const a = web.material.albedo_textures;
      const layers = new THREE.DataArrayTexture(new Float32Array(files[a.file]), a.width, a.height, a.layers);
      layers.format = THREE.RGBAFormat;
      layers.type = THREE.FloatType;
      layers.minFilter = layers.magFilter = THREE.NearestFilter;
      layers.generateMipmaps = false;
      layers.needsUpdate = true;
      uniforms.u_albedo_textures = { value: layers };
      this.programs.materials = this._materials(sources["three_materials.vert"], sources["three_materials.frag"]);
    }
    this.mesh = new THREE.Mesh(geometry, this._program());
    this.mesh.name = web.scene.name;
    this.mesh.onBeforeRender = (renderer, scene, camera) => this._update(renderer, camera);
    this.object = new THREE.Group();
    this.object.name = `prt: ${web.scene.name}`;
    this.object.add(this.mesh);
    // Depth first (options.depthPrepass, default on): a forward material runs its networks for every
    // fragment that passes the depth test, so without it hidden surfaces drawn first cost networks
    // too; with it, one network per pixel, as the page's deferred transfer pass.
    if (options.depthPrepass !== false) {
      const depth = (side) => new THREE.ShaderMaterial({
        name: "prt depth pre-pass", side, colorWrite: false, vertexShader: PREPASS_VERTEX, fragmentShader: "void main() { gl_FragColor = vec4(0.0); }",
      });
      this.prepass = new THREE.Mesh(geometry, [depth(THREE.FrontSide), depth(THREE.DoubleSide)]);
      this.prepass.name = `${web.scene.name} (depth pre-pass)`;
      this.prepass.renderOrder = -1;  // before the opaque meshes of the same render order (the app's default 0)
      this.object.add(this.prepass);
    }
    this.object.userData.prt = this;
  }

  _materials(vertexShader, fragmentShader) {
    const make = (side) => new THREE.ShaderMaterial({ name: `prt ${this.web.scene.name}`, vertexShader, fragmentShader, uniforms: this.uniforms, side });
    return [make(THREE.FrontSide), make(THREE.DoubleSide)];  // the two groups share one set of uniforms
  }

  _program() {
    return this._material === "scene" && this.web.material.per_object ? this.programs.materials : this.programs.plain;
  }

  // The light in world space (16 x 3): the env map's or the probe's SH, turned by `rotation` about +Y.
  worldLight() {
    let sh;
    if (this._probe) {
      const c = this._probe.sh.coefficients, k = this._probe.intensity;
      sh = Array.from({ length: 16 }, (_, i) => (i < 9 ? [c[i].x * k, c[i].y * k, c[i].z * k] : [0, 0, 0]));
    } else {
      sh = this.web.lighting.envmaps[this._envmap].sh;
    }
    return applyRows(shRotationY(this.web.lighting.rotation_fourier, (this._rotation * Math.PI) / 180), sh);
  }

  _update(renderer, camera) {
    const frame = renderer.info.render.frame;
    const world = this.mesh.matrixWorld;
    const inverse = new THREE.Matrix4().copy(world).invert();
    this.uniforms.u_eye.value.setFromMatrixPosition(camera.matrixWorld).applyMatrix4(inverse);
    if (frame === this._frame && !this._dirty) return;
    this._frame = frame;
    this._dirty = false;
    // The light in the scene's own frame: L_local(w) = L_world(R w) for the object's world rotation R.
    const q = new THREE.Quaternion();
    world.decompose(new THREE.Vector3(), q, new THREE.Vector3());
    const e = new THREE.Matrix4().makeRotationFromQuaternion(q).elements;  // column-major
    const r = [[e[0], e[4], e[8]], [e[1], e[5], e[9]], [e[2], e[6], e[10]]];
    let light = this.worldLight();
    if (r.some((row, i) => row.some((v, j) => Math.abs(v - identity3[i][j]) > 1e-9))) light = applyRows(shRotation(r), light);
    shadingUniforms(this.web, light, this.materialValues(), this.uniforms);
  }

  materialValues() {  // the uniform material (the page's materialOf)
    const m = this.web.material;
    if (this._material === "scene") return m.scene;
    if (this._material === "diffuse") return { kind: "diffuse", albedo: m.glossy.albedo, specular: m.scene.specular, exponent: m.scene.exponent };
    return { kind: "glossy", albedo: m.glossy.albedo, specular: m.glossy.specular, exponent: this._exponent };
  }

  get envmap() { return this._envmap; }
  get rotation() { return this._rotation; }
  set rotation(degrees) { this._rotation = Number(degrees); this._dirty = true; }
  get exposure() { return this.uniforms.u_exposure.value; }
  set exposure(value) { this.uniforms.u_exposure.value = Number(value); }

  setEnvmap(name) {
    if (!this.envmaps.includes(name)) throw new PRTError(`envmap must be one of ${this.envmaps.join(", ")}, got "${name}"`);
    this._envmap = name;
    this._probe = null;
    this._dirty = true;
  }

  // Light from a THREE.LightProbe (its L2 SH times its intensity; the fourth band is zero), read at every frame.
  setLightProbe(probe) {
    if (!probe || !probe.sh || probe.sh.coefficients.length !== 9) throw new PRTError("setLightProbe: a THREE.LightProbe is needed");
    this._probe = probe;
    this._dirty = true;
  }

  // "scene" (as built, per object where the scene has materials), "diffuse" or "glossy" (the page's Phong lobe).
  setMaterial(kind, exponent = this._exponent) {
    if (!["scene", "diffuse", "glossy"].includes(kind)) throw new PRTError(`material must be scene, diffuse or glossy, got "${kind}"`);
    if (!this.web.material.exponents.includes(exponent)) throw new PRTError(`exponent must be one of ${this.web.material.exponents.join(", ")}`);
    this._material = kind;
    this._exponent = exponent;
    this.mesh.material = this._program();
    this._dirty = true;
  }

  // The current light as a THREE.LightProbe (its first three bands), for the app's other meshes.
  lightProbe() {
    const light = this.worldLight();
    const sh = new THREE.SphericalHarmonics3();
    for (let i = 0; i < 9; ++i) sh.coefficients[i].set(...light[i]);
    return new THREE.LightProbe(sh, 1);
  }

  // An env map's image as an equirectangular THREE.DataTexture (linear float) and the
  // scene.backgroundRotation that shows it as the page does (its +Y up, turned with `rotation`).
  background(name = this._envmap) {
    const image = this.web.lighting.envmaps[name].image;
    if (!image) return null;
    if (!this._backgrounds.has(name)) {
      const t = new THREE.DataTexture(decodeRGBE(new Uint8Array(this._files[image.file]), image.width, image.height), image.width, image.height,
        THREE.RGBAFormat, THREE.FloatType);
      t.mapping = THREE.EquirectangularReflectionMapping;
      t.colorSpace = THREE.LinearSRGBColorSpace;
      t.magFilter = t.minFilter = THREE.LinearFilter;
      t.needsUpdate = true;
      this._backgrounds.set(name, t);
    }
    // The page samples the map at toMap d (u = 0.5 at -Z); three at R^T d with u = 0.25 at -Z: R = (S toMap)^T, S a quarter turn.
    const th = (this._rotation * Math.PI) / 180, c = Math.cos(th), s = Math.sin(th);
    const toMap = [[c, 0, s], [0, 1, 0], [-s, 0, c]].map((row) => [0, 1, 2].map((j) => row.reduce((a, v, k) => a + v * this.web.lighting.envmaps[name].rotation[k][j], 0)));
    const S = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]];
    const st = S.map((row) => [0, 1, 2].map((j) => row.reduce((a, v, k) => a + v * toMap[k][j], 0)));
    const m = new THREE.Matrix4().set(st[0][0], st[1][0], st[2][0], 0, st[0][1], st[1][1], st[2][1], 0, st[0][2], st[1][2], st[2][2], 0, 0, 0, 0, 1);
    return { texture: this._backgrounds.get(name), rotation: new THREE.Euler().setFromRotationMatrix(m) };
  }

  dispose() {
    this.geometry.dispose();
    for (const list of [...Object.values(this.programs), this.prepass ? this.prepass.material : []]) for (const m of list) m.dispose();
    for (const t of this._backgrounds.values()) t.dispose();
    for (const name of ["prt_weights", "u_material_table", "u_albedo_textures"]) if (this.uniforms[name]) this.uniforms[name].value.dispose();
  }
}

// Load the scene prt-web wrote into the folder at `url` (relative to the document).  Options:
// envmap (a name of web.json's lighting.envmaps), rotation (degrees), exposure, material, exponent,
// renderer (a THREE.WebGLRenderer: its limits are checked before the weights are fetched),
// depthPrepass (default true: a depth-only draw first, so the networks run once per pixel).
export async function loadPRT(url, options = {}) {
  const base = new URL(url.endsWith("/") ? url : `${url}/`, document.baseURI);
  const web = await fetchWeb(base);
  if (options.renderer) {
    const max = options.renderer.capabilities.maxTextureSize, w = web.weights;
    if (w && (w.width > max || w.height > max)) {
      throw new PRTError(`${w.file}: the networks' weights need a ${w.width} x ${w.height} texture, over this browser's limit of ${max} x ${max}`);
    }
  }
  const names = [web.geometry.file];
  if (web.weights) names.push(web.weights.file);
  if (web.material.albedo_textures) names.push(web.material.albedo_textures.file);
  for (const e of Object.values(web.lighting.envmaps)) if (e.image) names.push(e.image.file);
  const programs = Object.keys(web.three.programs);
  const [binaries, texts] = await Promise.all([
    Promise.all(names.map((n) => fetchBytes(base, web, n))),
    Promise.all(programs.map((n) => fetchText(base, web, web.three.programs[n]))),
  ]);
  const prt = new PRTScene(web, Object.fromEntries(names.map((n, i) => [n, binaries[i]])), Object.fromEntries(programs.map((n, i) => [n, texts[i]])),
    options);
  if (options.envmap !== undefined) prt.setEnvmap(options.envmap);
  if (options.rotation !== undefined) prt.rotation = options.rotation;
  if (options.exposure !== undefined) prt.exposure = options.exposure;
  if (options.material !== undefined) prt.setMaterial(options.material, options.exponent);
  return prt;
}

// A renderer's shader errors as one line (three.js logs them and goes on): set on the renderer
// before the first frame; `report` gets "shaders/three.frag: does not compile ...".
export function reportShaderErrors(renderer, report) {
  renderer.debug.onShaderError = (gl, program, vertex, fragment) => {
    const log = (shader) => (gl.getShaderInfoLog(shader) || "").trim().split("\n")[0];
    const which = !gl.getShaderParameter(fragment, gl.COMPILE_STATUS) ? ["three.frag", log(fragment)]
      : !gl.getShaderParameter(vertex, gl.COMPILE_STATUS) ? ["three.vert", log(vertex)] : ["three.vert + three.frag", (gl.getProgramInfoLog(program) || "").trim().split("\n")[0]];
    report(`shaders/${which[0]}: does not compile in this browser's WebGL2 (${which[1] || "no log"})`);
  };
}
