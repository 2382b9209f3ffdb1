// Real-time preview of the interpolated material (paper Sec. 5.1 in spirit): a sphere shaded in
// the fragment shader from the table sent by the server at reduced resolution (float16, layout
// (3, n_h, n_d, n_p), uploaded as an RGB 3D texture n_p x n_d x n_h), with MERL's half/diff
// lookup as in mitsuba_manifold/bsdf.py (merl_angles, merl_bin) and trilinear interpolation
// between bins. Lighting: an environment map (the shipped studio of hdri.py, or the scene's own
// environment seen from its camera, /api/env) integrated in every pixel by a polar quadrature
// about the mirror direction (rings of samples, finer near the mirror direction, each reading
// the environment prefiltered to its solid angle: a mip level), so that a sharp lobe and a
// diffuse one are both smooth; plus the key light the user drags (off by default).
// The drawing runs in a worker (preview_worker.js) that owns the canvas; this side keeps the
// table (the plots read it: value), the light and the sphere's size, and asks for draws.
"use strict";

const FULL_AFTER = 150;   // ms at rest before the sphere is drawn in full (setFast)
const NO_WEBGL = "WebGL 2 is not available to a worker in this browser: the preview sphere is off; the rest of the page works.";

class MaterialPreview {
  constructor(canvas, message) {
    this.canvas = canvas;
    this.message = message;
    this.key = [0.55, 0.6, 0.58];
    this.keyPower = 0.0;             // irradiance of the key light (the user's light; off by default)
    this.lighting = "studio";        // studio (the shipped HDRI), scene (the basis's own environment), key
    this.rotation = 0;               // the environment's rotation about the vertical, radians
    this.exposure = 0;
    this.table = null;               // { halfs: Uint16Array (3, n_h, n_d, n_p), layout } for the plots
    this.fast = false;
    this.full = canvas.width;        // the sphere's size at rest (pixels); a quarter while a drag runs
    this.size = canvas.width;
    this.envReady = false;
    this.pending = false;            // a draw asked for and not yet done
    this.serial = 0;
    this.draws = 0;   // sphere redraws (tools/bench.py explore --browser)
    this.worker = null;
    if (!canvas.transferControlToOffscreen || typeof Worker === "undefined") {
      this.fail(NO_WEBGL);
      return;
    }
    const offscreen = canvas.transferControlToOffscreen();
    this.worker = new Worker("/static/preview_worker.js");
    this.worker.onmessage = (ev) => this.answer(ev.data);
    this.worker.onerror = (ev) => this.fail("WebGL preview failed: " + (ev.message || "the worker did not start"));
    this.worker.postMessage({ type: "init", canvas: offscreen }, [offscreen]);
    this.bindLight();
    this.loadEnvironment();
    this.draw();
  }

  answer(m) {
    if (m.type === "drawn") { this.draws++; if (m.serial === this.serial) this.pending = false; }
    else if (m.type === "env") { this.envReady = true; }
    else if (m.type === "failed") this.fail(m.message === "no webgl2" ? NO_WEBGL : "WebGL preview failed: " + m.message);
  }

  fail(text) {
    if (this.worker) this.worker.terminate();
    this.worker = null;
    this.pending = false;
    this.message.textContent = text;
    this.message.classList.add("warn");
    this.canvas.style.display = "none";
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
    if (kind === "key") { this.draw(); return ""; }
    if (kind === "studio") { if (this.studio) this.setEnvironment(this.studio); return ""; }
    const r = await fetch("/api/env?" + new URLSearchParams({ basis: basis || "" }));
    if (!r.ok) { let m = r.statusText; try { m = (await r.json()).error; } catch (e) { /* not JSON */ } return m; }
    const meta = JSON.parse(r.headers.get("X-Env"));
    if (this.lighting !== kind) return "";
    this.sceneLight = meta.lights.length ? meta.lights[0] : null;   // the scene's point light, as the key
    this.setEnvironment({ pixels: new Uint16Array(await r.arrayBuffer()), width: meta.width, height: meta.height });
    return "";
  }

  // An equirectangular map (float16 RGB, top row up); the worker makes its mip levels.
  setEnvironment(envmap) {
    if (!this.worker) return;
    this.envReady = false;
    this.worker.postMessage({ type: "env", pixels: envmap.pixels.slice().buffer, width: envmap.width, height: envmap.height });
    this.draw();
  }

  // The key light of the next draw: [direction, RGB irradiance].
  keyLight() {
    if (this.lighting === "scene") return this.sceneLight ? [this.sceneLight.dir, this.sceneLight.irradiance] : [[0, 0, 1], [0, 0, 0]];
    const k = this.key, n = Math.hypot(...k);
    return [k.map((v) => v / n), [this.keyPower, this.keyPower, this.keyPower]];
  }

  // halfs: ArrayBuffer of float16 values, layout (3, n_h, n_d, n_p)
  setTable(halfs, layout) {
    const src = new Uint16Array(halfs);
    this.table = { halfs: src, layout };
    if (!this.worker) return;
    const copy = src.slice().buffer;   // the worker's own (moved to it, not copied again)
    this.worker.postMessage({ type: "table", halfs: copy, layout: { dims: layout.dims, full_dims: layout.full_dims, strides: layout.strides } }, [copy]);
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

  // While a drag runs the sphere is drawn at a quarter of its size with the coarse quadrature, in
  // full once it has rested for FULL_AFTER ms (a drag that starts again meanwhile skips it).
  setFast(fast) {
    if (!this.worker) return;
    clearTimeout(this.fullTimer);
    const size = fast ? Math.round(this.full / 4) : this.full;
    if (this.size === size && this.fast === fast) return;
    const apply = () => { this.fast = fast; this.size = size; this.draw(); };
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

  // A small PNG of the sphere as last drawn (favourites, compare).
  snapshot() { return this.worker ? this.canvas.toDataURL("image/png") : null; }

  // Ask the worker for a draw with the current parameters (it draws the newest of those queued).
  draw() {
    if (!this.worker) return;
    const [keyDir, keyPow] = this.keyLight();
    this.pending = true;
    this.worker.postMessage({ type: "draw", serial: ++this.serial, params: {
      size: this.size, fast: this.fast, env: this.lighting !== "key", keyDir, keyPow, rotation: this.rotation, exposure: this.exposure } });
  }
}
