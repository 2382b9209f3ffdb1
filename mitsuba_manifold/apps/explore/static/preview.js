// Real-time preview of the interpolated material (paper Sec. 5.1 in spirit): a sphere shaded in
// the fragment shader from the table sent by the server at reduced resolution (float16, layout
// (3, n_h, n_d, n_p) as a 3D texture n_p x n_d x 3*n_h), with MERL's half/diff lookup as in
// mitsuba_manifold/bsdf.py (merl_angles, merl_bin) and trilinear interpolation between bins.
"use strict";

const PREVIEW_VS = `#version 300 es
in vec2 pos; out vec2 uv;
void main() { uv = pos; gl_Position = vec4(pos, 0.0, 1.0); }`;

const PREVIEW_FS = `#version 300 es
precision highp float; precision highp sampler3D;
uniform sampler3D brdf;
uniform vec3 fullDims;   // (n_h, n_d, n_p) of the full table
uniform vec3 strides;    // bins of the full table per texel
uniform vec3 texDims;    // (n_h, n_d, n_p) of the reduced table
uniform vec3 keyDir;
uniform float exposure;
in vec2 uv; out vec4 color;
const float PI = 3.14159265358979;
const float HALF_PI = 1.5707963267949;
const float SCALE = 1.08;   // the sphere's radius is 1 / SCALE of the half-width

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
// position in the reduced texture, whose texel t holds full bin t * stride.
vec3 lookup(vec3 wi, vec3 wo) {
  vec3 a = merlAngles(wi, wo);
  vec3 c = vec3(sqrt(clamp(a.x / HALF_PI, 0.0, 1.0)) * fullDims.x,
                a.y / HALF_PI * fullDims.y,
                a.z / PI * fullDims.z);
  vec3 r = clamp((c - 0.5) / strides + 0.5, vec3(0.5), texDims - 0.5);   // texel units
  vec3 rgb;
  for (int k = 0; k < 3; k++) {
    float z = (float(k) * texDims.x + r.x) / (3.0 * texDims.x);
    rgb[k] = texture(brdf, vec3(r.z / texDims.z, r.y / texDims.y, z)).r;
  }
  return max(rgb, vec3(0.0));   // manifold_brdf clamps negative values the same way
}

vec3 shade(vec3 n, vec3 v, vec3 l, float power) {
  vec3 t = normalize(abs(n.y) < 0.99 ? cross(vec3(0.0, 1.0, 0.0), n) : cross(vec3(1.0, 0.0, 0.0), n));
  vec3 b = cross(n, t);
  vec3 wi = vec3(dot(l, t), dot(l, b), dot(l, n));
  vec3 wo = vec3(dot(v, t), dot(v, b), dot(v, n));
  if (wi.z <= 0.0 || wo.z <= 0.0) return vec3(0.0);
  return lookup(wi, wo) * wi.z * power;
}

vec3 srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}

void main() {
  vec2 p = uv * SCALE;
  float r2 = dot(p, p);
  if (r2 > 1.0) {
    float g = 0.07 + 0.035 * (1.0 - length(uv) * 0.5) + 0.02 * uv.y;
    color = vec4(vec3(g), 1.0);
    return;
  }
  vec3 n = vec3(p, sqrt(1.0 - r2));
  vec3 v = vec3(0.0, 0.0, 1.0);
  vec3 L = shade(n, v, normalize(keyDir), PI)                       // key light, irradiance pi
         + shade(n, v, normalize(vec3(-0.6, 0.25, 0.75)), 0.25 * PI) // weak fill
         + shade(n, v, normalize(vec3(0.1, 0.9, -0.35)), 0.35 * PI); // rim from behind
  // (tests/test_explore.py mirrors this shading in NumPy)
  color = vec4(srgb(L * exp2(exposure)), 1.0);
}`;

class MaterialPreview {
  constructor(canvas, message) {
    this.canvas = canvas;
    this.message = message;
    this.key = [0.55, 0.6, 0.58];
    this.exposure = 0;
    this.layout = null;
    this.draws = 0;   // sphere redraws (tools/bench.py explore --browser)
    this.gl = canvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true });
    if (!this.gl) {
      this.fail("WebGL 2 is not available in this browser: the preview sphere is off; the rest of the page works.");
      return;
    }
    try { this.init(); } catch (e) { this.fail("WebGL preview failed: " + e.message); return; }
    this.bindLight();
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
    this.tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_3D, this.tex);
    for (const [k, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR],
                          [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE],
                          [gl.TEXTURE_WRAP_R, gl.CLAMP_TO_EDGE]]) gl.texParameteri(gl.TEXTURE_3D, k, v);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.R16F, 1, 1, 3, 0, gl.RED, gl.HALF_FLOAT, new Uint16Array(3));
    this.u = {};
    for (const name of ["brdf", "fullDims", "strides", "texDims", "keyDir", "exposure"])
      this.u[name] = gl.getUniformLocation(prog, name);
    gl.uniform1i(this.u.brdf, 0);
    this.setLayout({ dims: [1, 1, 1], full_dims: [1, 1, 1], strides: [1, 1, 1] });
  }

  setLayout(layout) {
    const gl = this.gl;
    this.layout = layout;
    gl.useProgram(this.prog);
    gl.uniform3fv(this.u.fullDims, layout.full_dims);
    gl.uniform3fv(this.u.strides, layout.strides);
    gl.uniform3fv(this.u.texDims, layout.dims);
  }

  // halfs: ArrayBuffer of float16 values, layout (3, n_h, n_d, n_p)
  setTable(halfs, layout) {
    if (!this.gl) return;
    const gl = this.gl;
    const [nh, nd, np] = layout.dims;
    gl.bindTexture(gl.TEXTURE_3D, this.tex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.R16F, np, nd, 3 * nh, 0, gl.RED, gl.HALF_FLOAT, new Uint16Array(halfs));
    this.setLayout(layout);
    this.message.textContent = "drag on the sphere to move the light";
    this.draw();
  }

  setExposure(ev) { this.exposure = ev; this.draw(); }

  // While a drag runs the sphere is drawn at half resolution (a quarter of the fragments: the
  // software rasteriser of a machine without a GPU keeps up), at full resolution once it rests.
  setFast(fast) {
    if (!this.gl) return;
    if (!this.full) this.full = this.canvas.width;
    const size = fast ? Math.round(this.full / 2) : this.full;
    if (this.canvas.width === size) return;
    this.canvas.width = this.canvas.height = size;
    this.draw();
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

  draw() {
    if (!this.gl || this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draws++;
      const gl = this.gl;
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.useProgram(this.prog);
      gl.uniform3fv(this.u.keyDir, this.key);
      gl.uniform1f(this.u.exposure, this.exposure);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    });
  }
}
