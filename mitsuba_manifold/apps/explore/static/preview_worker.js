// The preview sphere's renderer, in a worker of its own (preview.js starts it): it owns the
// sphere's canvas (an OffscreenCanvas) and its WebGL 2 context, so that the draw and, on a machine
// without a GPU, the read-back of each frame for the page's compositor never hold up the page's
// thread (pointer moves, scene frames). The page sends the table, the environment and the light;
// the worker draws at most once per message batch and answers {type: "drawn", serial}.
"use strict";

importScripts("half.js");

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

// The environment's quadrature (rings x samples per ring) at rest and while a drag runs.
const QUADRATURE = { full: [12, 8], fast: [5, 5] };

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

const R = { gl: null, canvas: null, u: {}, envInfo: null, params: null, serial: 0, scheduled: false };

function init(canvas) {
  R.canvas = canvas;
  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
  if (!gl) throw new Error("no webgl2");   // the page says so in its own words
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
  R.tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_3D, R.tex);
  linear(gl.TEXTURE_3D);
  gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGB16F, 1, 1, 1, 0, gl.RGB, gl.HALF_FLOAT, new Uint16Array(3));
  gl.activeTexture(gl.TEXTURE1);
  R.envTex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, R.envTex);
  linear(gl.TEXTURE_2D);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB16F, 1, 1, 0, gl.RGB, gl.HALF_FLOAT, new Uint16Array(3));
  gl.activeTexture(gl.TEXTURE0);
  for (const name of ["brdf", "env", "fullDims", "strides", "texDims", "keyDir", "keyPow", "rings", "azimuths",
                      "envTexel", "envMaxLod", "envRot", "envShown", "exposure"])
    R.u[name] = gl.getUniformLocation(prog, name);
  gl.uniform1i(R.u.brdf, 0);
  gl.uniform1i(R.u.env, 1);
  R.prog = prog;
  R.gl = gl;
  setLayout({ dims: [1, 1, 1], full_dims: [1, 1, 1], strides: [1, 1, 1] });
}

function setLayout(layout) {
  const gl = R.gl;
  gl.uniform3fv(R.u.fullDims, layout.full_dims);
  gl.uniform3fv(R.u.strides, layout.strides);
  gl.uniform3fv(R.u.texDims, layout.dims);
}

// halfs: float16 values, layout (3, n_h, n_d, n_p); uploaded as RGB texels n_p x n_d x n_h
function setTable(halfs, layout) {
  const gl = R.gl, src = new Uint16Array(halfs);
  const [nh, nd, np] = layout.dims, n = nh * nd * np;
  const rgb = new Uint16Array(3 * n);
  for (let i = 0, j = 0; i < n; i++, j += 3) { rgb[j] = src[i]; rgb[j + 1] = src[n + i]; rgb[j + 2] = src[2 * n + i]; }
  gl.activeTexture(gl.TEXTURE0);
  gl.bindTexture(gl.TEXTURE_3D, R.tex);
  gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGB16F, np, nd, nh, 0, gl.RGB, gl.HALF_FLOAT, rgb);
  setLayout(layout);
}

// An equirectangular map (float16 RGB, top row up) with its mip levels (2x2 box filter per level).
function setEnvironment(pixels, width, height) {
  const gl = R.gl, rgb = new Float32Array(pixels.length);
  for (let i = 0; i < pixels.length; i++) rgb[i] = HALF_TO_FLOAT[pixels[i]];
  const levels = mipLevels(rgb, width, height);
  gl.activeTexture(gl.TEXTURE1);
  gl.bindTexture(gl.TEXTURE_2D, R.envTex);
  levels.forEach((l, k) => {
    const half = new Uint16Array(l.data.length);
    for (let i = 0; i < l.data.length; i++) half[i] = toHalf(l.data[i]);
    gl.texImage2D(gl.TEXTURE_2D, k, gl.RGB16F, l.width, l.height, 0, gl.RGB, gl.HALF_FLOAT, half);
  });
  gl.activeTexture(gl.TEXTURE0);
  R.envInfo = { texel: 2 * Math.PI / width, maxLod: levels.length - 1 };
}

// One draw with the newest parameters (p: size, fast, env, keyDir, keyPow, rotation, exposure).
function draw() {
  R.scheduled = false;
  const gl = R.gl, p = R.params;
  if (!gl || !p) return;
  if (R.canvas.width !== p.size) { R.canvas.width = R.canvas.height = p.size; }
  const env = p.env && R.envInfo !== null;
  const [rings, azimuths] = QUADRATURE[p.fast ? "fast" : "full"];
  gl.viewport(0, 0, p.size, p.size);
  gl.uniform3fv(R.u.keyDir, p.keyDir);
  gl.uniform3fv(R.u.keyPow, p.keyPow);
  gl.uniform1i(R.u.rings, env ? rings : 0);
  gl.uniform1i(R.u.azimuths, azimuths);
  gl.uniform1f(R.u.envTexel, R.envInfo ? R.envInfo.texel : 1);
  gl.uniform1f(R.u.envMaxLod, R.envInfo ? R.envInfo.maxLod : 0);
  gl.uniform2f(R.u.envRot, Math.cos(p.rotation), Math.sin(p.rotation));
  gl.uniform1f(R.u.envShown, env ? 0.2 : 0.0);
  gl.uniform1f(R.u.exposure, p.exposure);
  gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  gl.finish();   // the frame is done (and committed) before the page hears of it
  postMessage({ type: "drawn", serial: R.serial });
}

// Messages of one batch are applied in order; the draw comes after them (a queue of draws
// while one runs collapses into one with the newest parameters).
onmessage = (ev) => {
  const m = ev.data;
  try {
    if (m.type === "init") { init(m.canvas); postMessage({ type: "ready" }); return; }
    if (!R.gl) return;
    if (m.type === "table") setTable(m.halfs, m.layout);
    else if (m.type === "env") { setEnvironment(new Uint16Array(m.pixels), m.width, m.height); postMessage({ type: "env" }); }
    else if (m.type === "draw") { R.params = m.params; R.serial = m.serial; }
    if (!R.scheduled && R.params) { R.scheduled = true; setTimeout(draw, 0); }
  } catch (e) {
    postMessage({ type: "failed", message: e.message });
  }
};
