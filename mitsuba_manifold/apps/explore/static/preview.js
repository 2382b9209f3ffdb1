// Real-time preview of the interpolated material (paper Sec. 5.1 in spirit): a sphere shaded in
// the fragment shader from the table sent by the server at reduced resolution (float16, layout
// (3, n_h, n_d, n_p), uploaded as an RGB 3D texture n_p x n_d x n_h), with MERL's half/diff
// lookup as in mitsuba_manifold/bsdf.py (merl_angles, merl_bin) and trilinear interpolation
// between bins. Lighting: an environment map (the shipped studio of hdri.py, or the scene's own
// environment seen from its camera, /api/env) integrated in every pixel by a polar quadrature
// about the mirror direction (rings of samples, finer near the mirror direction, each reading
// the environment prefiltered to its solid angle: a mip level), so that a sharp lobe and a
// diffuse one are both smooth; plus the key light the user drags (off by default).
"use strict";

const PREVIEW_VS = `#version 300 es
in vec2 pos; out vec2 uv;
void main() { uv = pos; gl_Position = vec4(pos, 0.0, 1.0); }`;

const PREVIEW_FS = `#version 300 es
precision highp float; precision highp sampler3D;
uniform sampler3D brdf;  // RGB, (n_p, n_d, n_h) texels
uniform sampler2D env;   // equirectangular environment, linear RGB, with its mip levels
uniform vec3 fullDims;   // (n_h, n_d, n_p) of the full table
uniform vec3 strides;    // bins of the full table per texel
uniform vec3 texDims;    // (n_h, n_d, n_p) of the reduced table
uniform vec3 keyDir;     // the key light: direction and RGB irradiance
uniform vec3 keyPow;
uniform int rings;       // the environment's quadrature: rings about the mirror direction ...
uniform int azimuths;    // ... and samples per ring (0 rings: no environment light)
uniform float envTexel;  // angle of one texel of the environment's finest level (radians)
uniform float envMaxLod;
uniform vec2 envRot;     // (cos, sin) of the environment's rotation about the vertical
uniform float envShown;  // brightness of the environment behind the sphere (0: none)
uniform float exposure;
in vec2 uv; out vec4 color;
const float PI = 3.14159265358979;
const float HALF_PI = 1.5707963267949;
const float SCALE = 1.08;   // the sphere's radius is 1 / SCALE of the half-width
const int MAX_RINGS = 12, MAX_AZIMUTHS = 10;

// Rusinkiewicz angles, as merl_angles in bsdf.py (atan2 keeps small angles exact).
vec3 merlAngles(vec3 wi, vec3 wo) {
  vec3 h = wi + wo;
  float rh = length(h.xy);
  float thetaH = atan(rh, h.z);
  float invLen = inversesqrt(rh * rh + h.z * h.z);
  float cph = rh > 0.0 ? h.x / rh : 1.0;
  float sph = rh > 0.0 ? h.y / rh : 0.0;
  float cth = h.z * invLen, sth = rh * invLen;
  float dx = (wi.x * cph + wi.y * sph) * cth - wi.z * sth;
  float dy = wi.y * cph - wi.x * sph;
  float dz = (wi.x * cph + wi.y * sph) * sth + wi.z * cth;
  float thetaD = atan(length(vec2(dx, dy)), dz);
  float phiD = atan(dy, dx);
  if (phiD < 0.0) phiD += PI;
  if (phiD >= PI) phiD -= PI;
  return vec3(thetaH, thetaD, phiD);
}

// Continuous bin coordinates of the full table (merl_bin: sqrt spacing in theta_h), then the
// position in the reduced texture, whose texel t holds full bin t * stride; one trilinear fetch.
vec3 lookup(vec3 wi, vec3 wo) {
  vec3 a = merlAngles(wi, wo);
  vec3 c = vec3(sqrt(clamp(a.x / HALF_PI, 0.0, 1.0)) * fullDims.x,
                a.y / HALF_PI * fullDims.y,
                a.z / PI * fullDims.z);
  vec3 r = clamp((c - 0.5) / strides + 0.5, vec3(0.5), texDims - 0.5);   // texel units
  return max(texture(brdf, r.zyx / texDims.zyx).rgb, vec3(0.0));   // manifold_brdf clamps negatives the same way
}

vec3 srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}

// Radiance of the environment from view-space direction d (y up, z towards the viewer),
// prefiltered to mip level lod.
vec3 envRadiance(vec3 d, float lod) {
  d = vec3(d.x * envRot.x - d.z * envRot.y, d.y, d.x * envRot.y + d.z * envRot.x);   // into the map's frame
  vec2 t = vec2((atan(d.x, d.z) + PI) / (2.0 * PI), acos(clamp(d.y, -1.0, 1.0)) / PI);
  return textureLod(env, t, clamp(lod, 0.0, envMaxLod)).rgb;
}

void main() {
  vec2 p = uv * SCALE;
  float r2 = dot(p, p);
  if (r2 > 1.0) {
    color = vec4(srgb(envRadiance(normalize(vec3(uv * 0.5, -1.0)), 0.0) * envShown * exp2(exposure)), 1.0);
    return;
  }
  vec3 n = vec3(p, sqrt(1.0 - r2));
  vec3 t = normalize(abs(n.y) < 0.99 ? cross(vec3(0.0, 1.0, 0.0), n) : cross(vec3(1.0, 0.0, 0.0), n));
  vec3 b = cross(n, t);
  vec3 wo = vec3(t.z, b.z, n.z);   // the view direction (0, 0, 1) in the local frame
  vec3 L = vec3(0.0);
  // the environment: ring k of the quadrature spans angles pi (k/R)^2 .. pi ((k+1)/R)^2 from
  // the mirror direction; each of its samples carries its share of the ring's solid angle
  vec3 m = vec3(-wo.x, -wo.y, wo.z);
  vec3 u1 = normalize(abs(m.z) < 0.99 ? cross(vec3(0.0, 0.0, 1.0), m) : cross(vec3(1.0, 0.0, 0.0), m));
  vec3 u2 = cross(m, u1);
  float R = float(rings), A = float(azimuths);
  for (int k = 0; k < MAX_RINGS; k++) {
    if (k >= rings) break;
    float e0 = PI * pow(float(k) / R, 2.0), e1 = PI * pow(float(k + 1) / R, 2.0);
    float theta = PI * pow((float(k) + 0.5) / R, 2.0);
    float dw = 2.0 * PI * (cos(e0) - cos(e1)) / A;
    float lod = log2(sqrt(dw) / envTexel) + 1.0;   // a footprint twice the spacing: neighbours overlap
    for (int j = 0; j < MAX_AZIMUTHS; j++) {
      if (j >= azimuths) break;
      float phi = 2.0 * PI * (float(j) + 0.5 * float(k % 2)) / A;
      vec3 wi = cos(theta) * m + sin(theta) * (cos(phi) * u1 + sin(phi) * u2);
      if (wi.z <= 0.0) continue;
      L += lookup(wi, wo) * wi.z * dw * envRadiance(wi.x * t + wi.y * b + wi.z * n, lod);
    }
  }
  vec3 wk = vec3(dot(keyDir, t), dot(keyDir, b), dot(keyDir, n));
  if (wk.z > 0.0) L += lookup(wk, wo) * wk.z * keyPow;
  color = vec4(srgb(L * exp2(exposure)), 1.0);
}`;

// half-float bits -> float (for the slice and lobe plots drawn from the same table)
const HALF_TO_FLOAT = (() => {
  const out = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    out[h] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return out;
})();

const FULL_AFTER = 150;   // ms at rest before the sphere is drawn in full (setFast)
// The environment's quadrature (rings x samples per ring) at rest and while a drag runs.
const QUADRATURE = { full: [12, 8], fast: [6, 6] };

// float -> half-float bits (the environment's mip levels are uploaded as RGB16F)
function toHalf(v) {
  const f = new Float32Array([v]), i = new Uint32Array(f.buffer)[0];
  const sign = (i >> 16) & 0x8000, e = ((i >> 23) & 0xff) - 127 + 15, m = i & 0x7fffff;
  if (e <= 0) return sign | (e < -10 ? 0 : ((m | 0x800000) >> (1 - e + 13)));
  if (e >= 31) return sign | 0x7c00;
  return sign | (e << 10) | (m >> 13);
}

// The mip levels of an equirectangular map (float RGB, width x height): 2x2 box filter per level.
function mipLevels(rgb, width, height) {
  const levels = [{ data: rgb, width, height }];
  while (width > 1 || height > 1) {
    const w = Math.max(1, width >> 1), h = Math.max(1, height >> 1), src = levels[levels.length - 1].data;
    const out = new Float32Array(3 * w * h);
    for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) for (let c = 0; c < 3; c++) {
      let sum = 0, count = 0;
      for (const [dy, dx] of [[0, 0], [0, 1], [1, 0], [1, 1]]) {
        const yy = Math.min(height - 1, 2 * y + dy), xx = Math.min(width - 1, 2 * x + dx);
        sum += src[3 * (yy * width + xx) + c]; count++;
      }
      out[3 * (y * w + x) + c] = sum / count;
    }
    levels.push({ data: out, width: w, height: h });
    width = w; height = h;
  }
  return levels;
}

class MaterialPreview {
  constructor(canvas, message) {
    this.canvas = canvas;
    this.message = message;
    this.key = [0.55, 0.6, 0.58];
    this.keyPower = 0.0;             // irradiance of the key light (the user's light; off by default)
    this.lighting = "studio";        // studio (the shipped HDRI), scene (the basis's own environment), key
    this.rotation = 0;               // the environment's rotation about the vertical, radians
    this.exposure = 0;
    this.layout = null;
    this.table = null;               // { halfs: Uint16Array (3, n_h, n_d, n_p), layout } for the plots
    this.fast = false;
    this.draws = 0;   // sphere redraws (tools/bench.py explore --browser)
    this.gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
    if (!this.gl) {
      this.fail("WebGL 2 is not available in this browser: the preview sphere is off; the rest of the page works.");
      return;
    }
    try { this.init(); } catch (e) { this.fail("WebGL preview failed: " + e.message); return; }
    this.bindLight();
    this.loadEnvironment();
    this.draw();
  }

  fail(text) {
    this.gl = null;
    this.message.textContent = text;
    this.message.classList.add("warn");
    this.canvas.style.display = "none";
  }

  init() {
    const gl = this.gl;
    const compile = (type, src) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, src); gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    };
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, PREVIEW_VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, PREVIEW_FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog;
    gl.useProgram(prog);
    const buf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    const loc = gl.getAttribLocation(prog, "pos");
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
    const linear = (target) => {
      for (const [k, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR],
                            [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE],
                            [gl.TEXTURE_WRAP_R, gl.CLAMP_TO_EDGE]]) gl.texParameteri(target, k, v);
    };
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.activeTexture(gl.TEXTURE0);
    this.tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_3D, this.tex);
    linear(gl.TEXTURE_3D);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGB16F, 1, 1, 1, 0, gl.RGB, gl.HALF_FLOAT, new Uint16Array(3));
    gl.activeTexture(gl.TEXTURE1);
    this.envTex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.envTex);
    linear(gl.TEXTURE_2D);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB16F, 1, 1, 0, gl.RGB, gl.HALF_FLOAT, new Uint16Array(3));
    gl.activeTexture(gl.TEXTURE0);
    this.u = {};
    for (const name of ["brdf", "env", "fullDims", "strides", "texDims", "keyDir", "keyPow", "rings", "azimuths",
                        "envTexel", "envMaxLod", "envRot", "envShown", "exposure"])
      this.u[name] = gl.getUniformLocation(prog, name);
    gl.uniform1i(this.u.brdf, 0);
    gl.uniform1i(this.u.env, 1);
    this.setLayout({ dims: [1, 1, 1], full_dims: [1, 1, 1], strides: [1, 1, 1] });
  }

  // The shipped environment (mitsuba_manifold/apps/explore/hdri.py).
  async loadEnvironment() {
    try {
      const desc = await (await fetch("/static/env/studio.json")).json();
      const pixels = new Uint16Array(await (await fetch("/static/env/studio.f16")).arrayBuffer());
      this.studio = { pixels, width: desc.width, height: desc.height };
      if (this.lighting === "studio") this.setEnvironment(this.studio);
    } catch (e) { this.message.textContent = "environment map not loaded (" + e.message + "): key light only"; }
  }

  // Light the sphere with "studio" (the shipped HDRI), "scene" (the basis's environment as its
  // camera sees it: /api/env) or "key" (the key light alone). Returns a message, or "" when done.
  async setLighting(kind, basis) {
    this.lighting = kind;
    if (kind === "key") { this.envReady = false; this.draw(); return ""; }
    if (kind === "studio") { if (this.studio) this.setEnvironment(this.studio); return ""; }
    const r = await fetch("/api/env?" + new URLSearchParams({ basis: basis || "" }));
    if (!r.ok) { let m = r.statusText; try { m = (await r.json()).error; } catch (e) { /* not JSON */ } return m; }
    const meta = JSON.parse(r.headers.get("X-Env"));
    if (this.lighting !== kind) return "";
    this.sceneLight = meta.lights.length ? meta.lights[0] : null;   // the scene's point light, as the key
    this.setEnvironment({ pixels: new Uint16Array(await r.arrayBuffer()), width: meta.width, height: meta.height });
    return "";
  }

  // Upload an equirectangular map (float16 RGB, top row up) with its mip levels.
  setEnvironment(envmap) {
    if (!this.gl) return;
    const { pixels, width, height } = envmap, rgb = new Float32Array(pixels.length);
    for (let i = 0; i < pixels.length; i++) rgb[i] = HALF_TO_FLOAT[pixels[i]];
    const gl = this.gl, levels = mipLevels(rgb, width, height);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.envTex);
    levels.forEach((l, k) => {
      const half = new Uint16Array(l.data.length);
      for (let i = 0; i < l.data.length; i++) half[i] = toHalf(l.data[i]);
      gl.texImage2D(gl.TEXTURE_2D, k, gl.RGB16F, l.width, l.height, 0, gl.RGB, gl.HALF_FLOAT, half);
    });
    gl.activeTexture(gl.TEXTURE0);
    this.envInfo = { texel: 2 * Math.PI / width, maxLod: levels.length - 1 };
    this.envReady = true;
    this.draw();
  }

  // The key light of the next draw: [direction, RGB irradiance].
  keyLight() {
    if (this.lighting === "scene") return this.sceneLight ? [this.sceneLight.dir, this.sceneLight.irradiance] : [[0, 0, 1], [0, 0, 0]];
    const k = this.key, n = Math.hypot(...k);
    return [k.map((v) => v / n), [this.keyPower, this.keyPower, this.keyPower]];
  }

  setLayout(layout) {
    const gl = this.gl;
    this.layout = layout;
    gl.useProgram(this.prog);
    gl.uniform3fv(this.u.fullDims, layout.full_dims);
    gl.uniform3fv(this.u.strides, layout.strides);
    gl.uniform3fv(this.u.texDims, layout.dims);
  }

  // halfs: ArrayBuffer of float16 values, layout (3, n_h, n_d, n_p); uploaded as RGB texels
  setTable(halfs, layout) {
    const src = new Uint16Array(halfs);
    this.table = { halfs: src, layout };
    if (!this.gl) return;
    const gl = this.gl;
    const [nh, nd, np] = layout.dims, n = nh * nd * np;
    const rgb = new Uint16Array(3 * n);
    for (let i = 0, j = 0; i < n; i++, j += 3) { rgb[j] = src[i]; rgb[j + 1] = src[n + i]; rgb[j + 2] = src[2 * n + i]; }
    gl.bindTexture(gl.TEXTURE_3D, this.tex);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGB16F, np, nd, nh, 0, gl.RGB, gl.HALF_FLOAT, rgb);
    this.setLayout(layout);
    this.message.textContent = "drag on the sphere to move the light";
    this.draw();
  }

  // The table's value (RGB, 1/sr) at bin indices of the reduced table.
  value(ih, id, ip) {
    const t = this.table, [nh, nd, np] = t.layout.dims, n = nh * nd * np, i = (ih * nd + id) * np + ip;
    return [HALF_TO_FLOAT[t.halfs[i]], HALF_TO_FLOAT[t.halfs[n + i]], HALF_TO_FLOAT[t.halfs[2 * n + i]]];
  }

  setExposure(ev) { this.exposure = ev; this.draw(); }
  setRotation(rad) { this.rotation = rad; this.draw(); }
  setKeyPower(p) { this.keyPower = p; this.draw(); }

  // While a drag runs the sphere is drawn at a third of its resolution with the coarse quadrature
  // (the software rasteriser of a machine without a GPU keeps up: its draw, read back on the page's
  // thread, was a third of that thread's time at half resolution), in full once it has rested for
  // FULL_AFTER ms (a full draw takes 100-200 ms there; a drag that starts again meanwhile skips it).
  setFast(fast) {
    if (!this.gl) return;
    if (!this.full) this.full = this.canvas.width;
    clearTimeout(this.fullTimer);
    const size = fast ? Math.round(this.full / 3) : this.full;
    if (this.canvas.width === size && this.fast === fast) return;
    const apply = () => { this.fast = fast; this.canvas.width = this.canvas.height = size; this.draw(); };
    if (fast) apply();
    else this.fullTimer = setTimeout(apply, FULL_AFTER);
  }

  bindLight() {
    const move = (ev) => {
      const r = this.canvas.getBoundingClientRect();
      const px = ((ev.clientX - r.left) / r.width) * 2 - 1, py = 1 - ((ev.clientY - r.top) / r.height) * 2;
      const d2 = px * px + py * py;
      this.key = d2 < 1 ? [px, py, Math.sqrt(1 - d2)] : [px, py, -(Math.sqrt(d2) - 1) * 2];
      this.draw();
    };
    let down = false;
    this.canvas.addEventListener("pointerdown", (ev) => { down = true; this.canvas.setPointerCapture(ev.pointerId); move(ev); });
    this.canvas.addEventListener("pointermove", (ev) => { if (down) move(ev); });
    this.canvas.addEventListener("pointerup", () => { down = false; });
  }

  // A small PNG of the sphere as drawn (favourites, compare).
  snapshot() { return this.gl ? this.canvas.toDataURL("image/png") : null; }

  draw() {   // at most once per displayed frame, and only when asked (something changed)
    if (!this.gl || this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draws++;
      const gl = this.gl, [keyDir, keyPow] = this.keyLight(), env = this.envReady && this.lighting !== "key";
      const [rings, azimuths] = QUADRATURE[this.fast ? "fast" : "full"];
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.useProgram(this.prog);
      gl.uniform3fv(this.u.keyDir, keyDir);
      gl.uniform3fv(this.u.keyPow, keyPow);
      gl.uniform1i(this.u.rings, env ? rings : 0);
      gl.uniform1i(this.u.azimuths, azimuths);
      gl.uniform1f(this.u.envTexel, this.envInfo ? this.envInfo.texel : 1);
      gl.uniform1f(this.u.envMaxLod, this.envInfo ? this.envInfo.maxLod : 0);
      gl.uniform2f(this.u.envRot, Math.cos(this.rotation), Math.sin(this.rotation));
      gl.uniform1f(this.u.envShown, env ? 0.2 : 0.0);
      gl.uniform1f(this.u.exposure, this.exposure);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    });
  }
}
