// prt-web.js: the page of a scene written by prt-web (prt.export.web).  One ES module, no
// dependencies: it reads web.json and the binary files beside it and renders the scene with WebGL2
// in the passes of the desktop runtime's "glsl" backend, with the same (generated) GLSL:
//   G-buffer (position, normal + segment, [material], [posed position]; depth)
//   -> transfer pass (every fragment's network; the blocks are the layers of one array texture)
//   -> shade pass (SH lighting, Phong lobe through the Gaunt light matrices)
//   -> background (the env map where the depth is 1) -> tone mapping into the canvas.
// Contract (docs/guides/web.md): query parameters eye, target, fov, size, envmap, exposure (a number
// or auto), background (+ rotation, material, exponent, frame, mode=orbit|walk, capture); body data-prt-state
// loading|ready|error; the message of an error in #prt-error; with capture=1 the first frame as a
// PNG data URL in #prt-capture.

const WEB_FORMAT = "prt-web";
const WEB_VERSION = 1;
const $ = (id) => document.getElementById(id);

class PageError extends Error {}

function fail(message) {  // the first error is the one shown (later ones follow from it)
  if (document.body.dataset.prtState === "error") return;
  const box = $("prt-error");
  box.textContent = String(message).split("\n")[0];
  box.hidden = false;
  document.body.dataset.prtState = "error";
}

// ------------------------------------------------------------------ files

async function fetchOk(name) {
  let response;
  try {
    response = await fetch(name, { cache: "no-cache" });
  } catch (err) {
    throw new PageError(`${name}: cannot be fetched (${err.message})`);
  }
  if (!response.ok) throw new PageError(`${name}: HTTP ${response.status} ${response.statusText || ""}(missing file?)`.replace("  ", " "));
  return response;
}

async function fetchBytes(web, name) {
  const expected = web.files[name];
  const data = await (await fetchOk(name)).arrayBuffer();
  if (expected !== undefined && data.byteLength !== expected) {
    throw new PageError(`${name}: ${data.byteLength} bytes, web.json says ${expected} (a corrupt or truncated file)`);
  }
  return data;
}

async function fetchWeb() {
  const text = await (await fetchOk("web.json")).text();
  let web;
  try {
    web = JSON.parse(text);
  } catch (err) {
    throw new PageError(`web.json: not valid JSON (${err.message})`);
  }
  if (!web || typeof web !== "object" || web.format !== WEB_FORMAT) throw new PageError(`web.json: not a prt-web file (format ${JSON.stringify(web && web.format)})`);
  if (!Number.isInteger(web.version) || web.version > WEB_VERSION) {
    throw new PageError(`web.json: format version ${web.version} is newer than this page reads (${WEB_VERSION}); write the page again with the prt-web that wrote web.json`);
  }
  for (const key of ["scene", "camera", "geometry", "transfer", "uniforms", "lighting", "material", "files", "programs"]) {
    if (!(key in web)) throw new PageError(`web.json: no "${key}" (a corrupt file)`);
  }
  return web;
}

// ------------------------------------------------------------------ small vector maths (float64)

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => scale(a, 1 / Math.hypot(a[0], a[1], a[2]));

function rotateAbout(axis, angle, v) {  // Rodrigues, right-handed (runtime/camera.py: _rotation)
  const k = unit(axis);
  const c = Math.cos(angle), s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
}

// The camera of runtime/camera.py: basis, OpenGL perspective, view-projection (column-major out).
function cameraBasis(cam) {
  const forward = unit(sub(cam.target, cam.eye));
  const right = unit(cross(forward, cam.up));
  return { forward, right, up: cross(right, forward) };
}

function viewProjection(cam, aspect) {
  const { forward: f, right: r, up: u } = cameraBasis(cam);
  const view = [
    [r[0], r[1], r[2], -dot(r, cam.eye)],
    [u[0], u[1], u[2], -dot(u, cam.eye)],
    [-f[0], -f[1], -f[2], dot(f, cam.eye)],
    [0, 0, 0, 1],
  ];
  const t = 1 / Math.tan((cam.fov * Math.PI) / 360);
  const n = cam.near, fa = cam.far;
  const proj = [[t / aspect, 0, 0, 0], [0, t, 0, 0], [0, 0, (fa + n) / (n - fa), (2 * fa * n) / (n - fa)], [0, 0, -1, 0]];
  const out = new Float32Array(16);
  for (let row = 0; row < 4; ++row) {
    for (let col = 0; col < 4; ++col) {
      let v = 0;
      for (let k = 0; k < 4; ++k) v += proj[row][k] * view[k][col];
      out[col * 4 + row] = v;  // column-major, as GLSL reads a mat4
    }
  }
  return out;
}

// ------------------------------------------------------------------ walking (runtime/camera.py: walk, fit_near)

// One first-person step: turn (yaw about up, positive to the left; pitch clamped), then move
// (forward along the level heading, right, up).  The twin of prt.runtime.camera.walk.
function walkCamera(cam, move, yaw, pitch, maxPitch) {
  const up = unit(cam.up);
  const f = unit(sub(cam.target, cam.eye));
  const current = Math.asin(Math.max(-1, Math.min(1, dot(f, up))));
  let heading = sub(f, scale(up, dot(f, up)));
  if (Math.hypot(...heading) < 1e-9) heading = scale(cameraBasis(cam).up, dot(f, up) > 0 ? -1 : 1);
  heading = unit(rotateAbout(up, yaw, unit(heading)));
  const angle = Math.max(-maxPitch, Math.min(maxPitch, current + pitch));
  const forward = add(scale(heading, Math.cos(angle)), scale(up, Math.sin(angle)));
  const right = cross(heading, up);
  const eye = add(add(add(cam.eye, scale(heading, move[0])), scale(right, move[1])), scale(up, move[2]));
  const distance = Math.hypot(...sub(cam.target, cam.eye));
  return { ...cam, eye, target: add(eye, scale(forward, distance)) };
}

function fitNear(cam, c) {  // an eye inside the scene's box: the interior near plane
  const inside = [0, 1, 2].every((i) => cam.eye[i] >= c.box[0][i] && cam.eye[i] <= c.box[1][i]);
  return inside && cam.near > c.walk_near ? { ...cam, near: c.walk_near } : cam;
}

const WALK_KEYS = {
  forward: ["KeyW", "ArrowUp"], back: ["KeyS", "ArrowDown"], left: ["KeyA", "ArrowLeft"], right: ["KeyD", "ArrowRight"],
  up: ["Space", "KeyE"], down: ["ControlLeft", "ControlRight", "KeyQ"], fast: ["ShiftLeft", "ShiftRight"],
};
const WALK_FAST = 4;  // runtime/viewer.py: WALK_FAST
const LOOK_SENSITIVITY = 0.005;  // radians per pixel (runtime/viewer.py)

function walkMove(held, speed, dt) {  // runtime/viewer.py: walk_move
  const has = (a) => WALK_KEYS[a].some((k) => held.has(k));
  const f = has("forward") - has("back"), r = has("right") - has("left"), u = has("up") - has("down");
  if (!(f || r || u)) return null;
  const step = (speed * Math.max(dt, 0) * (has("fast") ? WALK_FAST : 1)) / Math.hypot(f, r, u);
  return [f * step, r * step, u * step];
}

// Auto exposure (runtime/exposure.py): the key over the log-average luminance of the covered pixels,
// smoothed in log space over tau seconds, the first frame exact.
function exposureFromLogMean(e, logMean) {
  if (logMean === null || !Number.isFinite(logMean) || logMean <= Math.log(e.eps) + 1e-9) return 1;
  return Math.min(Math.max(e.key / Math.exp(logMean), e.range[0]), e.range[1]);
}

function adaptExposure(view, target, now) {
  const a = view.adapt;
  if (a.value === null || a.tau === 0) a.value = target;
  else a.value = Math.exp(Math.log(a.value) + (Math.log(target) - Math.log(a.value)) * (1 - Math.exp(-Math.max(now - a.time, 0) / 1000 / a.tau)));
  a.time = now;
  a.target = target;
  return a.value;
}

// ------------------------------------------------------------------ lighting (SH)

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

function rotationY(theta) {  // the viewer's light rotation (runtime/viewer.py: _rotation_y)
  const c = Math.cos(theta), s = Math.sin(theta);
  return [[c, 0, s], [0, 1, 0], [-s, 0, c]];
}

const matmul3 = (a, b) => a.map((row) => [0, 1, 2].map((j) => row[0] * b[0][j] + row[1] * b[1][j] + row[2] * b[2][j]));

// The uniforms of shading.glsl (prt.runtime.shading.shader_uniforms), from the rotated lighting.
function shadingUniforms(web, light, material) {
  const n = light.length;
  const m = [0, 1, 2].map(() => Array.from({ length: n }, () => new Float64Array(n)));
  for (const [i, j, k, g] of web.lighting.gaunt) for (let c = 0; c < 3; ++c) m[c][k][j] += light[i][c] * g;
  const matrix = new Float32Array(48 * 16);
  for (let c = 0; c < 3; ++c) for (let bi = 0; bi < 4; ++bi) for (let bj = 0; bj < 4; ++bj) {
    const b = 16 * c + 4 * bi + bj;
    for (let col = 0; col < 4; ++col) for (let row = 0; row < 4; ++row) matrix[b * 16 + col * 4 + row] = m[c][4 * bi + row][4 * bj + col];
  }
  const lobe = web.material.lobes[exponentKey(material.exponent)];
  if (!lobe) throw new PageError(`web.json: no Phong lobe for exponent ${material.exponent}`);
  return {
    u_light: Float32Array.from(light.flat()),
    u_light_matrix: matrix,
    u_lobe: Float32Array.from(lobe),
    u_albedo: Float32Array.from(material.albedo),
    u_specular: Float32Array.from(material.specular),
    u_material_kind: [web.material.kinds.indexOf(material.kind)],
  };
}

function exponentKey(e) {  // Python's repr of a float, as web_assets._key writes the lobes' keys
  return Number.isInteger(e) ? `${e}.0` : String(e);
}

// ------------------------------------------------------------------ WebGL helpers

function compile(gl, type, source, name) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    const log = (gl.getShaderInfoLog(shader) || "no log").trim().split("\n")[0];
    throw new PageError(`shaders/${name}: does not compile in this browser's WebGL2 (${log})`);
  }
  return shader;
}

class Program {
  constructor(gl, sources, vertexName, fragmentName) {
    this.gl = gl;
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, sources[vertexName], vertexName));
    gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, sources[fragmentName], fragmentName));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
      throw new PageError(`shaders/${vertexName} + ${fragmentName}: do not link (${(gl.getProgramInfoLog(p) || "").trim().split("\n")[0]})`);
    }
    this.program = p;
    this.uniforms = new Map();
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); ++i) {
      const info = gl.getActiveUniform(p, i);
      this.uniforms.set(info.name.replace(/\[0\]$/, ""), { type: info.type, location: gl.getUniformLocation(p, info.name) });
    }
  }

  use() { this.gl.useProgram(this.program); return this; }

  attribute(name) { return this.gl.getAttribLocation(this.program, name); }

  // Set a uniform by name (the program must be in use); one the compiler dropped is skipped, as the desktop does.
  set(name, value) {
    const u = this.uniforms.get(name);
    if (!u) return this;
    const gl = this.gl;
    const v = typeof value === "number" ? [value] : value;
    switch (u.type) {
      case gl.FLOAT: gl.uniform1fv(u.location, v); break;
      case gl.FLOAT_VEC2: gl.uniform2fv(u.location, v); break;
      case gl.FLOAT_VEC3: gl.uniform3fv(u.location, v); break;
      case gl.FLOAT_VEC4: gl.uniform4fv(u.location, v); break;
      case gl.FLOAT_MAT3: gl.uniformMatrix3fv(u.location, false, v); break;
      case gl.FLOAT_MAT4: gl.uniformMatrix4fv(u.location, false, v); break;
      case gl.INT_VEC2: gl.uniform2iv(u.location, Int32Array.from(v)); break;
      default: gl.uniform1iv(u.location, Int32Array.from(v));  // int, bool and sampler uniforms
    }
    return this;
  }
}

function texture2D(gl, format, width, height, data = null, filter = gl.NEAREST) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  gl.texStorage2D(gl.TEXTURE_2D, 1, format, width, height);
  if (data) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, width, height, gl.RGBA, gl.FLOAT, data);
  return tex;
}

function textureArray(gl, width, height, layers, data = null) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
  gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA32F, width, height, layers);
  if (data) gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, 0, width, height, layers, gl.RGBA, gl.FLOAT, data);
  return tex;
}

function framebuffer(gl, attach, depth = null) {
  const fbo = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
  attach.forEach((a, i) => {
    if (a.layer === undefined) gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, a.texture, 0);
    else gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, a.texture, 0, a.layer);
  });
  if (depth) gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.TEXTURE_2D, depth, 0);
  gl.drawBuffers(attach.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
  const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
  if (status !== gl.FRAMEBUFFER_COMPLETE) throw new PageError(`this browser cannot render into ${attach.length} float targets (framebuffer status 0x${status.toString(16)})`);
  return fbo;
}

function bindTextures(gl, list) {  // [[texture, unit, target?], ...]
  for (const [tex, unit, target] of list) {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(target || gl.TEXTURE_2D, tex);
  }
}

function decodeRGBE(bytes, width, height) {  // byte * 2^(e - 136), as OpenCV reads .hdr (web_assets.rgbe_bytes)
  const out = new Float32Array(width * height * 4);
  for (let i = 0; i < width * height; ++i) {
    const e = bytes[4 * i + 3];
    const f = e ? Math.pow(2, e - 136) : 0;
    out[4 * i] = bytes[4 * i] * f;
    out[4 * i + 1] = bytes[4 * i + 1] * f;
    out[4 * i + 2] = bytes[4 * i + 2] * f;
    out[4 * i + 3] = 1;
  }
  return out;
}

// ------------------------------------------------------------------ the renderer

class WebRenderer {
  constructor(gl, web, files, sources) {
    this.gl = gl;
    this.web = web;
    this.blocks = web.transfer.blocks;
    this.perObjectTable = Boolean(web.material.table);
    this.deformable = Boolean(web.deformation);
    this.size = 0;
    this.limits = {};
    for (const k of ["MAX_TEXTURE_SIZE", "MAX_DRAW_BUFFERS", "MAX_COLOR_ATTACHMENTS", "MAX_TEXTURE_IMAGE_UNITS", "MAX_FRAGMENT_UNIFORM_VECTORS", "MAX_ARRAY_TEXTURE_LAYERS"]) {
      this.limits[k] = gl.getParameter(gl[k]);
    }
    this.checkLimits();
    const targets = this.blocks > 4 && this.limits.MAX_DRAW_BUFFERS >= 8 ? 8 : 4;
    this.targetsPerDraw = targets;
    this.programs = {
      gbuffer: new Program(gl, sources, "gbuffer.vert", "gbuffer.frag"),
      transfer: new Program(gl, sources, "fullscreen.vert", `transfer${targets}.frag`),
      shade: new Program(gl, sources, "fullscreen.vert", "shade.frag"),
      background: new Program(gl, sources, "background.vert", "background.frag"),
      display: new Program(gl, sources, "fullscreen.vert", "display.frag"),
      exposure: new Program(gl, sources, "fullscreen.vert", "log_luminance.frag"),
    };
    if (sources["shade_materials.frag"]) this.programs.shadeMaterials = new Program(gl, sources, "fullscreen.vert", "shade_materials.frag");
    this.emptyVao = gl.createVertexArray();
    this.buildGeometry(files["geometry.bin"]);
    this.buildStaticTextures(files);
    this.setStaticUniforms();
    this.poses = files["poses.bin"] || null;
    this.envmapTextures = new Map();
    this.envmapFiles = files;
  }

  checkLimits() {
    const web = this.web, L = this.limits;
    const w = web.weights;
    if (w && (w.width > L.MAX_TEXTURE_SIZE || w.height > L.MAX_TEXTURE_SIZE)) {
      throw new PageError(`${w.file}: the networks' weights need a ${w.width} x ${w.height} texture, over this browser's limit of ${L.MAX_TEXTURE_SIZE} x ${L.MAX_TEXTURE_SIZE}`);
    }
    const a = web.material.albedo_textures;
    if (a && (a.width > L.MAX_TEXTURE_SIZE || a.height > L.MAX_TEXTURE_SIZE || a.layers > L.MAX_ARRAY_TEXTURE_LAYERS)) {
      throw new PageError(`${a.file}: albedo textures of ${a.width} x ${a.height} x ${a.layers}, over this browser's limit of ${L.MAX_TEXTURE_SIZE} x ${L.MAX_TEXTURE_SIZE} x ${L.MAX_ARRAY_TEXTURE_LAYERS}`);
    }
    const gbufferTargets = 2 + Number(Boolean(web.material.table)) + Number(Boolean(web.deformation));
    if (L.MAX_DRAW_BUFFERS < gbufferTargets) throw new PageError(`the G-buffer needs ${gbufferTargets} render targets, this browser offers ${L.MAX_DRAW_BUFFERS}`);
    if (this.blocks > 4 * L.MAX_ARRAY_TEXTURE_LAYERS) throw new PageError("the transfer does not fit this browser's array textures");
    const g = web.uniforms.gbuffer;
    const vectors = g.prt_kd_nodes.length + g.prt_kd_roots.length + 2 * g.prt_segment_min.length + 24;
    if (vectors > L.MAX_FRAGMENT_UNIFORM_VECTORS) throw new PageError(`the segment tables need ${vectors} fragment uniform vectors, this browser offers ${L.MAX_FRAGMENT_UNIFORM_VECTORS}`);
    if (L.MAX_FRAGMENT_UNIFORM_VECTORS < 230) throw new PageError(`the shading needs 230 fragment uniform vectors, this browser offers ${L.MAX_FRAGMENT_UNIFORM_VECTORS}`);
  }

  buildGeometry(bytes) {
    const gl = this.gl, g = this.web.geometry, p = this.programs.gbuffer;
    const section = (name) => bytes.slice(g[name].offset, g[name].offset + g[name].bytes);
    this.corners = g.corners;
    this.closed = g.closed;
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const attach = (data, attributes, stride) => {
      const buffer = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      for (const [name, size, offset, integer] of attributes) {
        const loc = p.attribute(name);
        if (loc < 0) continue;
        gl.enableVertexAttribArray(loc);
        if (integer) gl.vertexAttribIPointer(loc, size, gl.INT, stride, offset);
        else gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride, offset);
      }
      return buffer;
    };
    this.recordBuffer = attach(section("records"), [["in_position", 3, 0], ["in_normal", 3, 12], ["in_face_normal", 3, 24]], 36);
    attach(section("info"), [["in_info", 2, 0, true]], 8);
    if (g.rest) attach(section("rest"), [["in_rest", 3, 0]], 12);
    if (g.albedo_uv) attach(section("albedo_uv"), [["in_albedo_uv", 2, 0]], 8);
    gl.bindVertexArray(null);
  }

  buildStaticTextures(files) {
    const gl = this.gl, web = this.web;
    if (web.weights) {
      this.weightData = new Float32Array(files[web.weights.file]);
      this.weights = texture2D(gl, gl.RGBA32F, web.weights.width, web.weights.height, this.weightData);
    }
    if (web.material.table) {
      const rows = web.material.table;  // (4, K, 4)
      this.materialTable = texture2D(gl, gl.RGBA32F, rows[0].length, rows.length, Float32Array.from(rows.flat(2)));
      const a = web.material.albedo_textures;
      this.albedoTextures = textureArray(gl, a.width, a.height, a.layers, new Float32Array(files[a.file]));
    }
  }

  setStaticUniforms() {
    const u = this.web.uniforms;
    const g = this.programs.gbuffer.use();
    g.set("prt_kd_nodes", u.gbuffer.prt_kd_nodes.flat()).set("prt_kd_roots", u.gbuffer.prt_kd_roots);
    g.set("prt_segment_min", u.gbuffer.prt_segment_min.flat()).set("prt_segment_max", u.gbuffer.prt_segment_max.flat());
    const t = this.programs.transfer.use();
    t.set("u_position", 0).set("u_normal", 1).set("prt_weights", 2);
    for (const [name, value] of Object.entries(u.transfer)) t.set(name, value.flat());
    for (const name of ["shade", "shadeMaterials"]) {
      const s = this.programs[name];
      if (!s) continue;
      s.use().set("u_position", 0).set("u_normal", 1).set("u_transfer", 2).set("u_gbuffer_material", 3).set("u_material_table", 4).set("u_albedo_textures", 5);
    }
    this.programs.background.use().set("u_envmap", 0);
    this.programs.display.use().set("u_image", 0);
    this.programs.exposure.use().set("u_frame", 0);
  }

  // The render targets of an n x n frame (kept per size: the page draws smaller while the view moves).
  use(n) {
    if (n === this.size) return;
    const gl = this.gl;
    if (n > this.limits.MAX_TEXTURE_SIZE) throw new PageError(`size ${n}: over this browser's limit of ${this.limits.MAX_TEXTURE_SIZE}`);
    this.sets = this.sets || new Map();
    if (!this.sets.has(n)) {
      const f32 = () => texture2D(gl, gl.RGBA32F, n, n);
      const t = { position: f32(), normal: f32(), valid: false };
      t.material = this.perObjectTable ? f32() : null;  // the G-buffer's material target (scenes with per-object materials)
      t.world = this.deformable ? f32() : null;  // the posed position (deformable scenes; target 0 holds the rest position)
      t.depth = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t.depth);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.DEPTH_COMPONENT24, n, n);
      const colour = [t.position, t.normal, ...(t.material ? [t.material] : []), ...(t.world ? [t.world] : [])];
      t.gbufferFbo = framebuffer(gl, colour.map((texture) => ({ texture })), t.depth);
      t.gbufferTargets = colour.length;
      t.transfer = textureArray(gl, n, n, this.blocks);
      t.transferFbos = [];
      for (let first = 0; first < this.blocks; first += this.targetsPerDraw) {
        const layers = Array.from({ length: Math.min(this.targetsPerDraw, this.blocks - first) }, (_, k) => ({ texture: t.transfer, layer: first + k }));
        t.transferFbos.push(framebuffer(gl, layers));
      }
      t.out = texture2D(gl, gl.RGBA32F, n, n);
      t.outFbo = framebuffer(gl, [{ texture: t.out }], t.depth);
      t.tileSize = Math.ceil(n / this.web.exposure.block);  // auto exposure: per-tile log-luminance sums
      t.tiles = texture2D(gl, gl.RGBA32F, t.tileSize, t.tileSize);
      t.tilesFbo = framebuffer(gl, [{ texture: t.tiles }]);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      this.sets.set(n, t);
    }
    this.targets = this.sets.get(n);
    Object.assign(this, this.targets);
    this.size = n;
  }

  invalidate() {  // the view or the pose changed: every size's transfer is stale
    for (const t of (this.sets || new Map()).values()) t.valid = false;
  }

  envmapTexture(name) {
    if (this.envmapTextures.has(name)) return this.envmapTextures.get(name);
    const gl = this.gl, image = this.web.lighting.envmaps[name].image;
    const linear = Boolean(gl.getExtension("OES_texture_float_linear"));
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    // float32 where the browser filters it (as the desktop); else half floats, always filterable
    gl.texImage2D(gl.TEXTURE_2D, 0, linear ? gl.RGBA32F : gl.RGBA16F, image.width, image.height, 0, gl.RGBA, gl.FLOAT,
      decodeRGBE(new Uint8Array(this.envmapFiles[image.file]), image.width, image.height));
    this.envmapTextures.set(name, tex);
    return tex;
  }

  setPose(frame) {
    const d = this.web.deformation, gl = this.gl;
    const start = frame * d.frame_bytes;
    const records = new Float32Array(this.poses, start, 9 * this.corners);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.recordBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, records);
    let at = start + 36 * this.corners;
    const flat = this.weightData, width = this.web.weights.width;
    const rows = new Set();
    for (const b of d.biases) {  // the first-layer bias of this pose's shape code (glsl backend: set_code)
      flat.set(new Float32Array(this.poses, at, 4 * b.texels), 4 * b.texel);
      at += 16 * b.texels;
      for (let y = Math.floor(b.texel / width); y <= Math.floor((b.texel + b.texels - 1) / width); ++y) rows.add(y);
    }
    gl.bindTexture(gl.TEXTURE_2D, this.weights);
    for (const y of rows) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, y, width, 1, gl.RGBA, gl.FLOAT, flat.subarray(4 * width * y, 4 * width * (y + 1)));
    this.invalidate();
  }

  gbufferPass(cam) {
    const gl = this.gl, n = this.size;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.gbufferFbo);
    gl.viewport(0, 0, n, n);
    gl.disable(gl.BLEND);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.depthMask(true);
    for (let i = 0; i < this.gbufferTargets; ++i) gl.clearBufferfv(gl.COLOR, i, i === 1 ? [0, 0, 0, -1] : [0, 0, 0, 0]);
    gl.clearBufferfv(gl.DEPTH, 0, [1]);
    const p = this.programs.gbuffer.use();
    p.set("u_view_projection", viewProjection(cam, 1)).set("u_eye", cam.eye);
    gl.bindVertexArray(this.vao);
    if (this.closed) {  // closed faces with back-face culling, then the two-sided ones without (runtime/gbuffer.py)
      gl.frontFace(gl.CCW);
      gl.cullFace(gl.BACK);
      gl.enable(gl.CULL_FACE);
      gl.drawArrays(gl.TRIANGLES, 0, this.closed);
      gl.disable(gl.CULL_FACE);
    }
    if (this.corners > this.closed) gl.drawArrays(gl.TRIANGLES, this.closed, this.corners - this.closed);
    gl.disable(gl.DEPTH_TEST);
  }

  transferPass() {
    const gl = this.gl, n = this.size;
    const p = this.programs.transfer.use();
    bindTextures(gl, [[this.position, 0], [this.normal, 1], ...(this.weights ? [[this.weights, 2]] : [])]);
    gl.bindVertexArray(this.emptyVao);
    this.transferFbos.forEach((fbo, part) => {
      gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
      gl.viewport(0, 0, n, n);
      p.set("u_part", part);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    });
  }

  shadePass(view) {
    const gl = this.gl, n = this.size;
    const perObject = view.material === "scene" && this.web.material.per_object;
    const p = (perObject ? this.programs.shadeMaterials : this.programs.shade).use();
    for (const [name, value] of Object.entries(view.shading)) p.set(name, value);
    p.set("u_eye", view.camera.eye);
    const textures = [[this.world || this.position, 0], [this.normal, 1], [this.transfer, 2, gl.TEXTURE_2D_ARRAY]];
    if (perObject) textures.push([this.material, 3], [this.materialTable, 4], [this.albedoTextures, 5, gl.TEXTURE_2D_ARRAY]);
    bindTextures(gl, textures);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.outFbo);
    gl.viewport(0, 0, n, n);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  backgroundPass(view) {
    const gl = this.gl, n = this.size, cam = view.camera;
    const { forward, right, up } = cameraBasis(cam);
    const half = Math.tan((cam.fov * Math.PI) / 360);
    const p = this.programs.background.use();
    p.set("u_to_map", view.toMap.flat()).set("u_forward", forward).set("u_right", right).set("u_up", up);
    p.set("u_half", [half, half]).set("u_size", [n, n]);
    bindTextures(gl, [[this.envmapTexture(view.envmap), 0]]);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.outFbo);
    gl.enable(gl.DEPTH_TEST);  // only where the G-buffer's depth is 1 (runtime/background.py)
    gl.depthFunc(gl.LEQUAL);
    gl.depthMask(false);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.depthMask(true);
    gl.disable(gl.DEPTH_TEST);
  }

  // The mean of log(EPS + L) over the covered pixels of the shaded frame (before the background; alpha
  // marks them), or null: shaders/log_luminance.frag sums tiles, their few texels are read back.
  exposurePass() {
    const gl = this.gl, n = this.size, m = this.tileSize;
    this.programs.exposure.use().set("u_size", [n, n]);
    bindTextures(gl, [[this.out, 0]]);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.tilesFbo);
    gl.viewport(0, 0, m, m);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    const data = new Float32Array(4 * m * m);
    gl.readPixels(0, 0, m, m, gl.RGBA, gl.FLOAT, data);
    let sum = 0, count = 0;
    for (let i = 0; i < m * m; ++i) { sum += data[4 * i]; count += data[4 * i + 1]; }
    return count > 0.5 ? sum / Math.round(count) : null;
  }

  displayPass(view, exposure) {  // the frame (maybe smaller than the canvas while the view moves) tone-mapped into the canvas
    const gl = this.gl, w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h);
    this.programs.display.use().set("u_window", [w, h]).set("u_exposure", exposure);
    bindTextures(gl, [[this.out, 0]]);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  // One frame of n x n pixels (default: the view's size) into the canvas; the networks run when the
  // view or the pose changed (or `networks`).  Returns its time in ms, to the GPU's finish (a
  // one-pixel read waits for it).
  frame(view, networks = false, n = view.size) {
    const gl = this.gl;
    const t0 = performance.now();
    this.use(n);
    const ran = networks || !this.targets.valid;
    if (ran) {
      this.gbufferPass(view.camera);
      this.transferPass();
      this.targets.valid = true;
    }
    this.shadePass(view);
    let exposure = view.exposure;
    if (exposure === "auto") {
      view.logMean = this.exposurePass();
      exposure = adaptExposure(view, exposureFromLogMean(this.web.exposure, view.logMean), performance.now()) * view.bias;
    }
    view.shownExposure = exposure;
    if (view.background && this.web.lighting.envmaps[view.envmap].image) this.backgroundPass(view);
    this.displayPass(view, exposure);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
    const ms = performance.now() - t0;
    const error = gl.getError();
    if (error !== gl.NO_ERROR) throw new PageError(`WebGL error 0x${error.toString(16)} while drawing the frame`);
    return { ms, networks: ran, size: n };
  }
}

// ------------------------------------------------------------------ the view: query, controls

function parseVector(text, name) {
  const v = text.split(",").map(Number);
  if (v.length !== 3 || !v.every(Number.isFinite)) throw new PageError(`query: ${name} must be three numbers X,Y,Z, got "${text}"`);
  return v;
}

function parseNumber(text, name, lo, hi) {
  const v = Number(text);
  if (!Number.isFinite(v) || v < lo || v > hi) throw new PageError(`query: ${name} must be a number in [${lo}, ${hi}], got "${text}"`);
  return v;
}

function parseQuery(web, search) {
  const q = new URLSearchParams(search);
  const c = web.camera;
  const envmaps = Object.keys(web.lighting.envmaps);
  const view = {
    base: { eye: c.eye, target: c.target, up: c.up, fov: c.fov, near: c.near, far: c.far },
    size: 512, envmap: web.lighting.default, exposure: web.exposure.default, bias: 1, background: web.lighting.background,
    mode: "orbit", adapt: { value: null, time: 0, target: null, tau: web.exposure.tau },
    rotation: 0, material: "scene", exponent: web.material.glossy.exponent, frame: 0, capture: q.get("capture") === "1",
  };
  if (q.has("eye")) view.base.eye = parseVector(q.get("eye"), "eye");
  if (q.has("target")) view.base.target = parseVector(q.get("target"), "target");
  if (q.has("fov")) view.base.fov = parseNumber(q.get("fov"), "fov", 1, 179);
  if (q.has("size")) {
    view.size = parseNumber(q.get("size"), "size", 1, 8192);
    if (!Number.isInteger(view.size)) throw new PageError(`query: size must be a whole number of pixels, got "${q.get("size")}"`);
  }
  if (q.has("envmap")) {
    view.envmap = q.get("envmap");
    if (!envmaps.includes(view.envmap)) throw new PageError(`query: envmap must be one of ${envmaps.join(", ")}, got "${view.envmap}"`);
  }
  if (q.has("exposure")) view.exposure = q.get("exposure") === "auto" ? "auto" : parseNumber(q.get("exposure"), "exposure", 0, 1e6);
  if (q.has("mode")) {
    view.mode = q.get("mode");
    if (!["orbit", "walk"].includes(view.mode)) throw new PageError(`query: mode must be orbit or walk, got "${view.mode}"`);
  }
  if (q.has("background")) {
    const b = q.get("background");
    if (b !== "black" && b !== "envmap") throw new PageError(`query: background must be black or envmap, got "${b}"`);
    view.background = b === "envmap";
  }
  if (q.has("rotation")) view.rotation = parseNumber(q.get("rotation"), "rotation", -360, 360);
  if (q.has("material")) {
    view.material = q.get("material");
    if (!["scene", "diffuse", "glossy"].includes(view.material)) throw new PageError(`query: material must be scene, diffuse or glossy, got "${view.material}"`);
  }
  if (q.has("exponent")) {
    view.exponent = Number(q.get("exponent"));
    if (!web.material.exponents.includes(view.exponent)) throw new PageError(`query: exponent must be one of ${web.material.exponents.join(", ")}, got "${q.get("exponent")}"`);
  }
  if (q.has("frame")) {
    const frames = web.deformation ? web.deformation.frames : 1;
    view.frame = parseNumber(q.get("frame"), "frame", 0, frames - 1);
    if (!Number.isInteger(view.frame)) throw new PageError(`query: frame must be a whole number, got "${q.get("frame")}"`);
  }
  const v = sub(view.base.target, view.base.eye);
  if (Math.hypot(...v) < 1e-9 || Math.hypot(...cross(v, view.base.up)) < 1e-9 * Math.hypot(...v)) {
    throw new PageError("query: eye and target must differ, and the view must not be parallel to up");
  }
  view.orbit = { yaw: 0, pitch: 0, zoom: 1 };
  view.walk = { ...view.base };  // the walking camera (mode walk)
  return view;
}

// The camera after the user's orbit: yaw about up through the target, pitch towards up, zoom.
function orbitCamera(view) {
  const b = view.base, o = view.orbit;
  let offset = sub(b.eye, b.target);
  const right = cameraBasis(b).right;
  offset = rotateAbout(right, -o.pitch, offset);
  offset = rotateAbout(b.up, o.yaw, offset);
  return { ...b, eye: add(b.target, scale(offset, o.zoom)) };
}

// The material the shading uses: the scene's (per object or uniform) or the page's override.
function materialOf(web, view) {
  const m = web.material;
  if (view.material === "scene") return m.scene;
  if (view.material === "diffuse") return { kind: "diffuse", albedo: m.glossy.albedo, specular: m.scene.specular, exponent: m.scene.exponent };
  return { kind: "glossy", albedo: m.glossy.albedo, specular: m.glossy.specular, exponent: view.exponent };
}

function prepare(web, view) {  // what the passes read from the view
  const env = web.lighting.envmaps[view.envmap];
  const theta = (view.rotation * Math.PI) / 180;
  const d = shRotationY(web.lighting.rotation_fourier, theta);
  const light = d.map((row) => [0, 1, 2].map((c) => row.reduce((s, v, j) => s + v * env.sh[j][c], 0)));
  view.camera = fitNear(view.mode === "walk" ? view.walk : orbitCamera(view), web.camera);
  view.light = light;
  view.toMap = matmul3(rotationY(theta), env.rotation);
  view.shading = shadingUniforms(web, light, materialOf(web, view));
  return view;
}

function formatBytes(n) {
  return n >= 1e6 ? `${(n / 1e6).toFixed(2)} MB` : `${Math.round(n / 1e3)} kB`;
}

function setupControls(page) {
  const { web, view, canvas } = page;
  const envmap = $("prt-envmap");
  for (const [name, e] of Object.entries(web.lighting.envmaps)) envmap.add(new Option(e.label, name));
  envmap.value = view.envmap;
  const exponent = $("prt-exponent");
  for (const e of web.material.exponents) exponent.add(new Option(String(e), String(e)));
  exponent.value = String(view.exponent);
  $("prt-rotation").value = String(view.rotation);
  $("prt-exposure").value = view.exposure === "auto" ? "0" : String(Math.log2(Math.max(view.exposure, 1e-9)));
  $("prt-exposure-auto").checked = view.exposure === "auto";
  $("prt-background").value = view.background ? "envmap" : "black";
  $("prt-material").value = view.material;
  const on = (id, event, f) => $(id).addEventListener(event, (e) => { f(e.target); page.request(); });
  on("prt-envmap", "change", (t) => { view.envmap = t.value; });
  on("prt-rotation", "input", (t) => { view.rotation = Number(t.value); });
  on("prt-exposure", "input", (t) => { if (view.exposure === "auto") view.bias = Math.pow(2, Number(t.value)); else view.exposure = Math.pow(2, Number(t.value)); });
  on("prt-exposure-auto", "change", (t) => {  // auto: the slider is a bias on the auto exposure
    view.exposure = t.checked ? "auto" : Math.pow(2, Number($("prt-exposure").value));
    view.bias = t.checked ? Math.pow(2, Number($("prt-exposure").value)) : 1;
    view.adapt.value = null;
  });
  on("prt-background", "change", (t) => { view.background = t.value === "envmap"; });
  on("prt-material", "change", (t) => { view.material = t.value; });
  on("prt-exponent", "change", (t) => { view.exponent = Number(t.value); });
  if (web.deformation) {
    $("prt-pose").hidden = false;
    const frame = $("prt-frame");
    frame.max = String(web.deformation.frames - 1);
    frame.value = String(view.frame);
    on("prt-frame", "input", (t) => page.pose(Number(t.value)));
    let timer = null;
    $("prt-play").addEventListener("change", (e) => {
      clearInterval(timer);
      if (e.target.checked) timer = setInterval(() => { page.pose((view.frame + 1) % web.deformation.frames); frame.value = String(view.frame); }, 100);
    });
  }
  setupWalk(page);
  // Orbit and zoom: one pointer (mouse or finger) orbits, two pinch, the wheel zooms; walking, one
  // pointer looks around and two move forward or back (a finger drag up walks forward).
  const pointers = new Map();
  let pinch = 0;
  const spread = () => { const [a, b] = [...pointers.values()]; return Math.hypot(a.x - b.x, a.y - b.y); };
  canvas.addEventListener("pointerdown", (e) => { canvas.setPointerCapture(e.pointerId); pointers.set(e.pointerId, { x: e.clientX, y: e.clientY }); if (pointers.size === 2) pinch = spread(); });
  canvas.addEventListener("pointermove", (e) => {
    const last = pointers.get(e.pointerId);
    if (!last) return;
    const dx = e.clientX - last.x, dy = e.clientY - last.y;
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    if (view.mode === "walk") {
      if (document.pointerLockElement === canvas) return;  // mouse look through movementX/Y (setupWalk)
      if (pointers.size === 1) view.walk = walkCamera(view.walk, [0, 0, 0], -dx * LOOK_SENSITIVITY, -dy * LOOK_SENSITIVITY, web.camera.max_pitch);
      else view.walk = walkCamera(view.walk, [(-dy / pointers.size) * web.camera.walk_speed * 0.01, 0, 0], 0, 0, web.camera.max_pitch);
    } else if (pointers.size === 1) {
      view.orbit.yaw -= dx * 0.01;
      view.orbit.pitch = Math.max(-1.4, Math.min(1.4, view.orbit.pitch + dy * 0.01));
    } else if (pointers.size === 2) {
      const now = spread();
      if (pinch > 0 && now > 0) view.orbit.zoom = Math.max(0.2, Math.min(5, view.orbit.zoom * (pinch / now)));
      pinch = now;
    }
    page.request(true, true);
  });
  const release = (e) => { pointers.delete(e.pointerId); pinch = pointers.size === 2 ? spread() : 0; };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); if (view.mode === "walk") return; view.orbit.zoom = Math.max(0.2, Math.min(5, view.orbit.zoom * Math.exp(e.deltaY * 0.001))); page.request(true, true); }, { passive: false });
  canvas.addEventListener("dblclick", () => { view.orbit = { yaw: 0, pitch: 0, zoom: 1 }; view.walk = { ...view.base }; page.request(true); });
}

// Walking: v switches orbit <-> walk; W A S D / arrows move, space / E up, ctrl / Q down, shift x4, at
// the scene's walking speed (web.json camera.walk_speed, prt.runtime.camera.walk_speed); a click
// locks the pointer for mouse look (Esc releases it), else a drag looks.
function setupWalk(page) {
  const { web, view, canvas } = page;
  const held = new Set();
  let last = null;
  const mode = $("prt-mode");
  const setMode = (m) => {
    if (m === view.mode) return;
    if (m === "walk") view.walk = { ...view.camera };  // walk on from the view on screen
    else { view.base = { ...view.walk }; view.orbit = { yaw: 0, pitch: 0, zoom: 1 }; }
    view.mode = m;
    mode.value = m;
    page.request(true);
  };
  mode.value = view.mode;
  mode.addEventListener("change", (e) => setMode(e.target.value));
  const typing = (e) => e.target && ["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName) && e.target.type !== "range";
  const tick = (now) => {
    if (!held.size || view.mode !== "walk") { last = null; return; }
    const dt = last === null ? 1 / 60 : Math.min((now - last) / 1000, 0.1);
    last = now;
    const move = walkMove(held, web.camera.walk_speed, dt);
    if (move) { view.walk = walkCamera(view.walk, move, 0, 0, web.camera.max_pitch); page.request(true, true); }
    requestAnimationFrame(tick);
  };
  window.addEventListener("keydown", (e) => {
    if (typing(e)) return;
    if (e.code === "KeyV" && !e.repeat) { setMode(view.mode === "walk" ? "orbit" : "walk"); return; }
    if (view.mode !== "walk" || !Object.values(WALK_KEYS).some((keys) => keys.includes(e.code))) return;
    e.preventDefault();
    const start = !held.size;
    held.add(e.code);
    if (start) requestAnimationFrame(tick);
  });
  window.addEventListener("keyup", (e) => held.delete(e.code));
  window.addEventListener("blur", () => held.clear());
  canvas.addEventListener("click", () => { if (view.mode === "walk" && canvas.requestPointerLock) { try { const p = canvas.requestPointerLock(); if (p && p.catch) p.catch(() => {}); } catch (err) { /* no lock: drag looks */ } } });
  document.addEventListener("mousemove", (e) => {
    if (view.mode !== "walk" || document.pointerLockElement !== canvas) return;
    view.walk = walkCamera(view.walk, [0, 0, 0], -e.movementX * LOOK_SENSITIVITY, -e.movementY * LOOK_SENSITIVITY, web.camera.max_pitch);
    page.request(true, true);
  });
}

// ------------------------------------------------------------------ the page

async function main() {
  if (location.protocol === "file:") return;  // the classic script in index.html has said why
  const web = await fetchWeb();
  const view = parseQuery(web, location.search);
  const canvas = $("prt-canvas");
  canvas.width = canvas.height = view.size;
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true, premultipliedAlpha: false });
  if (!gl) throw new PageError("this browser offers no WebGL2 (needed to draw the scene on the GPU)");
  if (!gl.getExtension("EXT_color_buffer_float")) throw new PageError("this browser's WebGL2 cannot render into float textures (EXT_color_buffer_float), which the G-buffer and the transfer need");
  canvas.addEventListener("webglcontextlost", (e) => { e.preventDefault(); fail("the WebGL context was lost (the GPU was reset or the tab ran out of GPU memory); reload the page"); });
  // Limits first (no download of what cannot be drawn), then every file at once.
  const probe = gl.getParameter(gl.MAX_TEXTURE_SIZE);
  if (web.weights && (web.weights.height > probe || web.weights.width > probe)) {
    throw new PageError(`${web.weights.file}: the networks' weights need a ${web.weights.width} x ${web.weights.height} texture, over this browser's limit of ${probe} x ${probe}`);
  }
  const names = [web.geometry.file];
  if (web.weights) names.push(web.weights.file);
  if (web.material.albedo_textures) names.push(web.material.albedo_textures.file);
  if (web.deformation) names.push(web.deformation.file);
  for (const e of Object.values(web.lighting.envmaps)) if (e.image) names.push(e.image.file);
  const programNames = Object.keys(web.programs);
  const [binaries, texts] = await Promise.all([
    Promise.all(names.map((n) => fetchBytes(web, n))),
    Promise.all(programNames.map(async (n) => {
      const file = web.programs[n];
      const text = await (await fetchOk(file)).text();
      if (web.files[file] !== undefined && new TextEncoder().encode(text).length !== web.files[file]) throw new PageError(`${file}: not the file web.json lists (a corrupt or changed file)`);
      return text;
    })),
  ]);
  const files = Object.fromEntries(names.map((n, i) => [n, binaries[i]]));
  const sources = Object.fromEntries(programNames.map((n, i) => [n, texts[i]]));
  const renderer = new WebRenderer(gl, web, files, sources);

  const s = web.scene;
  document.title = `${s.name}: PRT in WebGL2`;
  $("prt-name").textContent = s.name;
  $("prt-size").textContent = `${s.triangles.toLocaleString("en")} triangles, ${s.segments} segments (${s.networks} networks)`
    + `${s.interreflection ? ", interreflection" : ""}; ${formatBytes(s.payload_bytes)} loaded`;
  const stats = $("prt-stats");
  const page = {
    web, view, canvas, renderer, frames: 0, networkMs: null, relightMs: null, pending: false, networks: false, moving: false, settle: null,
    // Ask for a frame at the next animation frame; `networks`: the view or the pose changed; `moving`:
    // the user is dragging, so the frame may be drawn smaller to keep up (full size once they stop).
    request(networks = false, moving = false) {
      if (networks) renderer.invalidate();
      this.moving = this.moving || moving;
      if (moving) {
        clearTimeout(this.settle);
        this.settle = setTimeout(() => this.request(false, false), 250);
      }
      if (this.pending) return;
      this.pending = true;
      requestAnimationFrame(() => {
        this.pending = false;
        const moving = this.moving;
        this.moving = false;
        try { this.draw(moving); } catch (err) { fail(err.message); }
      });
    },
    // The size of a frame while the view moves: about 40 ms of networks, given the last full frame's time.
    movingSize() {
      const ms = this.networkMs || 0;
      if (ms <= 40) return view.size;
      return Math.max(64, Math.min(view.size, 16 * Math.round((view.size * Math.sqrt(40 / ms)) / 16)));
    },
    draw(moving = false, networks = false) {
      const r = renderer.frame(prepare(web, view), networks, moving ? this.movingSize() : view.size);
      this.frames += 1;
      const a = view.adapt;  // auto exposure still on its way to this view's: another (re-shaded) frame
      if (view.exposure === "auto" && a.target !== null && Math.abs(Math.log(a.value / a.target)) > 0.01) this.request();
      if (r.size !== view.size) return r;  // a reduced frame while moving: the figures stay those of full frames
      if (r.networks) this.networkMs = r.ms; else this.relightMs = r.ms;
      const ms = this.networkMs;
      const fps = 1000 / ms;
      stats.textContent = `${ms.toFixed(1)} ms a frame (${fps.toFixed(fps >= 10 ? 0 : fps >= 1 ? 1 : 2)} FPS) at ${view.size} x ${view.size}`
        + (this.relightMs === null ? "" : `; relight ${this.relightMs.toFixed(1)} ms`);
      stats.dataset.frameMs = ms.toFixed(3);
      stats.dataset.fps = (1000 / ms).toFixed(2);
      if (this.relightMs !== null) stats.dataset.relightMs = this.relightMs.toFixed(3);
      return r;
    },
    pose(frame) {
      view.frame = frame;
      renderer.setPose(frame);
      this.request(true);
    },
  };
  if (web.deformation) renderer.setPose(view.frame);
  setupControls(page);
  document.body.dataset.loadMs = performance.now().toFixed(1);  // files fetched, programs linked
  page.draw();
  document.body.dataset.firstFrameMs = performance.now().toFixed(1);
  if (view.capture) $("prt-capture").textContent = canvas.toDataURL("image/png");
  // For tests and benchmarks: frames on demand (the networks rerun when asked), the computed uniforms.
  window.prtWeb = {
    web, view, limits: renderer.limits,
    frame(networks = true) { return page.draw(false, networks); },
    benchmark(frames = 10, networks = true) {
      const times = [];
      for (let i = 0; i < frames; ++i) times.push(renderer.frame(prepare(web, view), networks).ms);
      return times;
    },
    // A target of the last full-size frame as float32 RGBA, base64, rows from the bottom (GL's order):
    // "position", "normal", "out" or a transfer block's index.
    read(which) {
      renderer.use(view.size);
      const t = renderer.targets, n = view.size, data = new Float32Array(4 * n * n);
      const fbo = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
      if (typeof which === "number") gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, t.transfer, 0, which);
      else gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t[which], 0);
      gl.readPixels(0, 0, n, n, gl.RGBA, gl.FLOAT, data);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.deleteFramebuffer(fbo);
      const bytes = new Uint8Array(data.buffer);
      let text = "";
      for (let i = 0; i < bytes.length; i += 0x8000) text += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
      return btoa(text);
    },
    uniforms() { prepare(web, view); return { u_light: Array.from(view.shading.u_light), u_light_matrix: Array.from(view.shading.u_light_matrix), u_lobe: Array.from(view.shading.u_lobe), to_map: view.toMap }; },
  };
  document.body.dataset.prtState = "ready";
}

window.addEventListener("error", (e) => fail(e.message || "a script error"));
window.addEventListener("unhandledrejection", (e) => fail((e.reason && e.reason.message) || String(e.reason)));
main().catch((err) => fail(err instanceof PageError ? err.message : `unexpected error: ${err && err.message ? err.message : err}`));
