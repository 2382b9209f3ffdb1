// The explorer page: latent map, scene frames over a websocket, material panel, paths, snippets,
// reference renders (the acquisition from a photo: acquire.js). No build step; talks only to the server that served it.
"use strict";

const $ = (id) => document.getElementById(id);
// Text of an element, changed only when it differs (a drag sets it on every move: no needless layout).
const setText = (el, text) => { if (el.textContent !== text) el.textContent = text; };
const fmtNum = (v, d = 3) => (Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-3 && v !== 0)) ? v.toExponential(2) : v.toFixed(d);
const LOCAL = ["127.0.0.1", "localhost", "[::1]"].includes(location.hostname);

const NUMBER = /^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$/;   // as the server takes them (no "1_0")

// The page's state (store.js: changed through update(), which draws the parts that follow it).
const state = {
  info: null, x: null, basis: null, exposure: 0, dims: [0, 1], map: null, mapImage: null,
  hover: -1, a: null, b: null, displayed: null, material: null, snippet: null, errors: [], zoom: null,
  filter: "", status: null, favs: [], compare: [], refine: null, reference: null,
  mapKey: null, moves: 0, dragging: false, liveUntil: 0, connected: false,
  // raw RGBA on this machine (exact, no encoding); JPEG when the page is viewed from elsewhere
  format: new URLSearchParams(location.search).get("format") || (LOCAL ? "rgba" : "jpeg"),
};

// ------------------------------------------------------------------ server access
async function api(path, options) {
  const r = await fetch(path, options);
  if (!r.ok) {
    let msg = r.statusText;
    try { msg = (await r.json()).error; } catch (e) { /* not JSON */ }
    throw new Error(msg);
  }
  return r;
}

// The header's status: one line. state.errors holds the errors not yet answered, each tied to its
// source (a kind of answer, "reference", "snippet", "link", ...; one per source): the next success
// of that source clears it (clearError). The header shows the latest of them, else state.status.
function setStatus(text, error = false, source = null) {
  if (!error) { update({ status: { text } }); return; }
  update({ errors: state.errors.filter((e) => source === null || e.source !== source).concat([{ text, source }]) });
}
function drawStatus() {
  const err = state.errors[state.errors.length - 1], text = err ? err.text : state.status ? state.status.text : "";
  const s = $("status");
  s.textContent = text;
  s.title = text;
  s.classList.toggle("error", !!err);
}
function clearError(source) {
  if (state.errors.some((e) => e.source === source)) update({ errors: state.errors.filter((e) => e.source !== source) });
}

let channel, preview;
const sameX = (a, b) => !!a && !!b && a.length === b.length && a.every((v, k) => v === b[k]);

function onMessage(meta, payload) {
  if (state.foreign) return;   // the server serves another manifold now (reconnected)
  if (meta.type === "error" && meta.kind === "route") { routeFailed(meta); return; }
  if (meta.type === "progress") { if (meta.kind === "route") routeProgress(meta); return; }
  if (meta.type === "error") { setStatus((meta.kind ? meta.kind + ": " : "") + meta.error, true, meta.kind); return; }
  clearError(meta.type);
  if (meta.type === "frame") drawFrame(meta, payload);
  else if (meta.type === "material") showMaterial(meta);
  else if (meta.type === "table" && preview) {
    // the full table of a point a new drag has left (a newer table asked for): not worth its upload
    if (!meta.coarse && live() && !channel.isCurrent("table", meta.seq)) return;
    if (!sameX(meta.x, state.previewX) || meta.coarse !== state.previewCoarse) { preview.setTable(payload, meta); drawPlots(); showGloss(); }
    state.previewCoarse = meta.coarse;   // redrawn only when it changed
    update({ previewX: meta.x });
  }
  else if (meta.type === "route") showRoute(meta);
  else if (meta.type === "snippet") showSnippet(meta);
  else if (meta.type === "map") showMap(meta, payload);
  else if (meta.type === "path") showPath(meta);
}

// ------------------------------------------------------------------ scene frames
async function drawFrame(meta, payload) {
  const c = $("scene");
  let bmp = null;
  if (meta.format !== "rgba") bmp = await createImageBitmap(new Blob([payload], { type: "image/" + meta.format }));
  if (state.displayed && state.displayed.seq > meta.seq) return;   // a newer frame was drawn meanwhile
  if (keepsRefined(meta)) return;   // refine.js: the exact image of this point is shown
  if (c.width !== meta.width || c.height !== meta.height) { c.width = meta.width; c.height = meta.height; }
  const ctx = c.getContext("2d");
  if (bmp) ctx.drawImage(bmp, 0, 0);
  else ctx.putImageData(new ImageData(new Uint8ClampedArray(payload), meta.width, meta.height), 0, 0);
  state.displayed = { x: meta.x, seq: meta.seq, exposure: meta.exposure, basis: meta.basis, at: performance.now() };
  drawStale();
  if (window.explore.trace) window.explore.trace.push({ x: meta.x, at: state.displayed.at, server_ms: meta.total_ms,
    round_trip_ms: meta.round_trip_ms });   // tools/bench.py explore --browser
  c.dataset.x = meta.x.join(",");
  const n = meta.n_images;
  $("timing").textContent = `${n} image${n === 1 ? "" : "s"} · blend ${meta.blend_ms.toFixed(1)} + tonemap ` +
    `${meta.tonemap_ms.toFixed(1)} + ${meta.format} ${meta.encode_ms.toFixed(1)} = ${meta.total_ms.toFixed(1)} ms on the server` +
    (meta.round_trip_ms ? ` · ${meta.round_trip_ms.toFixed(0)} ms round trip` : "");
}

// What the map of the current point shows: the slice (the coordinates off the map's axes,
// for q > 2), the axes and the zoom. Moving within the slice needs no new map.
function sliceKey() {
  const off = state.x.filter((_, k) => !state.dims.includes(k));
  return JSON.stringify([state.dims, off, state.zoom]);
}

function frameRequest() { return { x: state.x, exposure: state.exposure, basis: state.basis, format: state.format }; }
function requestFrame() { channel.send(Object.assign({ type: "frame" }, frameRequest()), ["frame"]); }   // the full frame of the point

// While a drag runs (pointer down on the map, a slider moving) the scene follows every move;
// the panel (material, snippet) and the sphere's table follow at most every LIVE[kind] ms, so
// that they do not take the frames' time (the sphere's table, its redraw and the panel cost the
// server, the page and a machine without a GPU more than a frame: four times a second; the
// snippet, a long text laid out again, once a second); when the drag rests (REST ms) the kinds
// not yet asked for the final point are asked for.
const LIVE = { table: 250, material: 250, snippet: 1000 }, REST = 120;
const asked = {};   // kind -> [time, x] of its last request

function live() { return state.dragging || performance.now() < state.liveUntil; }

// One message per move: every kind of answer the point needs (the map only for a new slice).
function sendMove(resting = false) {
  moveQueued = false;
  const now = performance.now(), dragging = !resting && live(), want = [];
  const held = dragging || state.dragging;   // pointer still down: frames stay summed (denoising takes 50-100 ms)
  for (const kind of ["frame", "table", "material", "snippet"]) {
    if (kind === "table" && state.info.tables !== "ready") continue;
    const last = asked[kind], d = kind === "frame" ? held : dragging;
    if (last && sameX(last[1], state.x) && !(last[2] && !d)) continue;   // a coarse answer is asked again at rest
    if (!d || !last || now - last[0] >= (LIVE[kind] || 0)) { want.push(kind); asked[kind] = [now, state.x, d && kind !== "snippet"]; }
  }
  // a new slice while a slider or the path scrubber moves it: a coarse map, the full one at rest;
  // a press on the map moves the slice once (to a material's whole point) and its drag stays in
  // that slice: the full map at once (a coarse one first would cost the drag's frames its time);
  // the page's first map: the coarse one first, the full one once it is shown (showMap)
  const key = sliceKey();
  if (key !== state.mapKey) { state.mapKey = key; state.mapCoarse = (dragging && !state.dragging) || !state.map; want.push("map"); }
  else if (state.mapCoarse && !dragging) { state.mapCoarse = false; want.push("map"); }
  if (preview) preview.setFast(state.dragging || dragging);   // a pointer held still keeps the drag's resolution
  owe(dragging);
  if (!want.length) return;
  state.moves++;
  // slice: false: the page draws the BRDF slice itself, from the table (plots.js)
  // coarse: while dragging the sphere's table has every other texel (an eighth of the bytes), a new
  // slice's map a quarter of the pixels, the material no distance to the closest measured one
  channel.send(Object.assign({ type: "move", want, dims: state.dims, extent: state.zoom, slice: false, coarse: dragging, held,
                               map_coarse: !!state.mapCoarse, folder: state.snippetFolder },
                             frameRequest()), want);
}
function owe(dragging) {   // kinds not asked for the point shown yet (counted by channel.pending())
  const kinds = ["material", "snippet"].concat(state.info.tables === "ready" ? ["table"] : []);
  channel.owed = kinds.filter((k) => !asked[k] || !sameX(asked[k][1], state.x) || (asked[k][2] && !dragging)).length;
  clearTimeout(state.restTimer);
  if (dragging) state.restTimer = setTimeout(() => sendMove(true), REST);   // no move for REST ms: resting
}
let moveQueued = false;
function scheduleMove() {   // at most one move per displayed frame of the browser
  if (moveQueued) return;
  moveQueued = true;
  requestAnimationFrame(() => { if (moveQueued) sendMove(); });
  setTimeout(() => { if (moveQueued) sendMove(); }, 100);   // rAF is paused in hidden tabs
}
function requestAll() { state.mapKey = null; for (const k in asked) delete asked[k]; scheduleMove(); }
function requestMap() {
  state.mapKey = sliceKey();
  channel.send({ type: "map", x: state.x, dims: state.dims, extent: state.zoom }, ["map"]);
}

// The point shown changes (a drag, a click, undo/redo, a name, a link, the path scrubber): the
// state first, then every part that follows the point (the views below), then its answers asked for.
function setX(x) {
  update({ x: x.slice() });
  scheduleMove();
}
// The parts of the page that follow the point (store.js).
function drawPoint() {
  // the point (and basis) in the address: a reload or a shared link comes back here (at most every
  // 200 ms: the browser rate-limits replaceState, and each call costs the drag milliseconds)
  clearTimeout(state.addressTimer);
  state.addressTimer = setTimeout(() => history.replaceState(null, "", "#x=" + state.x.join(",") +
                                  (state.basis ? "&basis=" + encodeURIComponent(state.basis) : "")), 200);
  updateSavePng();
  updateSliders();
  if (state.map && sliceKey() !== state.drawnSlice) drawMap();   // q > 2: the materials fade by their distance to the slice
  else placeCursor();
}
view(["x"], drawPoint);
view(["x", "material", "snippet"], showPoint);
view(["filter"], () => buildGallery());   // shelf.js: the tiles matching the search
view(["status", "errors"], drawStatus);
view(["connected", "x", "displayed", "previewX"], drawStale);

// While the server is away, what it showed for another point than the one chosen is dimmed: the
// scene and the sphere keep their last images, which are not the point's (the panel is dimmed
// by showPoint whenever its answer is not the point's).
function drawStale() {
  if (state.foreign) return;   // stays dimmed: reload
  const away = !state.connected && !!state.x;
  $("scene").classList.toggle("stale", away && !(state.displayed && sameX(state.displayed.x, state.x)));
  $("sphere").classList.toggle("stale", away && !sameX(state.previewX, state.x));
  document.body.classList.toggle("disconnected", !state.connected);
}

// The websocket is back (the server restarted, or the network came back): the page asks again for
// its whole state. The server's facts (/api/info: tables, thumbnails), every answer for the point
// (frame, sphere table, material, snippet, map) and the refinement; the errors of the time
// away are dropped (each comes back if its cause is still there), a shared link's excepted.
async function reconnected() {
  update({ errors: state.errors.filter((e) => e.source === "link" || e.source === "server") });
  let info;
  try { info = await (await api("/api/info")).json(); }
  catch (e) { return; }   // gone again: the next reconnection asks again
  const same = (a, b) => JSON.stringify(a) === JSON.stringify(b), was = state.info;
  if (info.manifold !== was.manifold || !same(info.latent, was.latent) || !same(info.names, was.names) ||
      !same(info.bases.map((b) => [b.name, b.folder]), was.bases.map((b) => [b.name, b.folder]))) {
    // another manifold or other bases: the map, names and lists of this page are not the server's
    state.foreign = true;   // its answers are for another manifold's points: none is shown
    setStatus("the server restarted with another manifold or other bases: reload the page (its point is in the address)", true, "server");
    document.body.classList.add("disconnected");
    for (const id of ["scene", "sphere"]) $(id).classList.add("stale");
    return;
  }
  state.info.tables = info.tables; state.info.thumbs = info.thumbs; state.info.refine_spp = info.refine_spp;
  update({ previewX: null });   // the sphere's table comes again, even for the same point
  state.previewCoarse = null;
  requestAll();
  if (state.info.tables === "loading") pollTables();
  if (state.refine || state.refineJob) { state.refineJob = null; update({ refine: null }); refineHere(); }
  if (state.route && state.route.computing && pathReady()) requestRoute();   // its request went with the old socket
  if ($("path-cmd").classList.contains("stale") && pathReady()) exportPath();
}

function updateSavePng() {
  $("save-png").href = "/api/frame?" + new URLSearchParams({ x: state.x.join(","), basis: state.basis,
                                                              exposure: state.exposure, format: "png" });
}

// The point shown: its name (a measured material) or coordinates, at once; the facts below
// (weights, albedo, ...) are marked stale until the answer for this point arrives.
function showPoint() {
  const name = materialName(state.x);
  setText($("material-name"), name ? name : "x = (" + state.x.map((v) => fmtNum(v)).join(", ") + ")");
  $("material-name").dataset.x = state.x.join(",");
  $("material-panel").classList.toggle("stale", !state.material || !sameX(state.material.x, state.x));
  $("use-box").classList.toggle("stale", !state.snippet || !sameX(state.snippet.x, state.x));
}

// ------------------------------------------------------------------ latent map
function showMap(meta, payload) {
  const url = URL.createObjectURL(new Blob([payload], { type: "image/png" }));
  const img = new Image();
  img.onload = () => {
    if (!channel.isCurrent("map", meta.seq) && state.map && state.map.seq > meta.seq) { URL.revokeObjectURL(url); return; }
    if (state.map && state.map.png) URL.revokeObjectURL(state.map.png);
    state.map = Object.assign({}, meta, { png: url, extent: state.zoom || meta.extent });
    state.mapImage = img; state.mapImageExtent = meta.extent;
    if (!state.zoom) state.fullExtent = meta.extent;
    drawMap();
    // a coarse map shown at rest (the page's first): the full one now
    if (state.mapCoarse && !live() && channel.isCurrent("map", meta.seq)) { state.mapCoarse = false; requestMap(); }
  };
  img.src = url;
  $("ramp").style.background = `linear-gradient(to right, ${meta.colormap.join(",")})`;
  $("ramp-lo").textContent = meta.albedo_range[0].toFixed(2);
  $("ramp-hi").textContent = meta.albedo_range[1].toFixed(2);
}

function toCanvas(p) {
  const [x0, x1, y0, y1] = state.map.extent, c = $("map");
  return [(p[state.dims[0]] - x0) / (x1 - x0) * c.width, (1 - (p[state.dims[1]] - y0) / (y1 - y0)) * c.height];
}
function fromCanvas(px, py) {
  const [x0, x1, y0, y1] = state.map.extent, c = $("map");
  const x = state.x.slice();
  x[state.dims[0]] = x0 + px / c.width * (x1 - x0);
  x[state.dims[1]] = y0 + (1 - py / c.height) * (y1 - y0);
  return x;
}

function nearestPoint(px, py, radius = 9) {
  let best = -1, bd = radius * radius;
  state.info.latent.forEach((p, i) => {
    const [cx, cy] = toCanvas(p), d = (cx - px) ** 2 + (cy - py) ** 2;
    if (d < bd) { bd = d; best = i; }
  });
  return best;
}

function drawMap() {
  const c = $("map"), ctx = c.getContext("2d");
  if (!state.map || !state.x) return;
  ctx.imageSmoothingEnabled = true;
  ctx.fillStyle = "#101216"; ctx.fillRect(0, 0, c.width, c.height);
  const [ix0, ix1, iy0, iy1] = state.mapImageExtent || state.map.extent, [x0, x1, y0, y1] = state.map.extent;
  ctx.drawImage(state.mapImage, (ix0 - x0) / (x1 - x0) * c.width, (1 - (iy1 - y0) / (y1 - y0)) * c.height,
                (ix1 - ix0) / (x1 - x0) * c.width, (iy1 - iy0) / (y1 - y0) * c.height);
  const { latent, names, albedos } = state.info;
  if (state.a && state.b) drawRoute(ctx);
  latent.forEach((p, i) => {
    const [px, py] = toCanvas(p);
    const a = albedos ? albedos[i] : [0.5, 0.5, 0.5];
    // q > 2: materials far from the slice (in the other coordinates) fade out
    const off = p.reduce((s, v, k) => s + (state.dims.includes(k) ? 0 : (v - state.x[k]) ** 2), 0);
    ctx.globalAlpha = i === state.hover ? 1 : Math.max(0.25, Math.exp(-off / 0.5));
    const sheet = state.thumbImage, t = state.thumbs, r = sheet ? (i === state.hover ? 11 : 8) : (i === state.hover ? 6 : 4);
    ctx.beginPath(); ctx.arc(px, py, r, 0, 2 * Math.PI);
    if (sheet) {   // the material's own thumbnail: its appearance (gloss, colour) on the map
      ctx.save(); ctx.clip();
      ctx.drawImage(sheet, (i % t.columns) * t.size, Math.floor(i / t.columns) * t.size, t.size, t.size, px - r, py - r, 2 * r, 2 * r);
      ctx.restore();
    } else {
      ctx.fillStyle = `rgb(${a.map((v) => Math.round(255 * Math.min(1, Math.max(0, v)) ** (1 / 2.2))).join(",")})`;
      ctx.fill();
    }
    ctx.lineWidth = 1.5; ctx.strokeStyle = i === state.hover ? "#fff" : "rgba(0,0,0,.85)"; ctx.stroke();
  });
  ctx.globalAlpha = 1;
  for (const [end, label] of [[state.a, "A"], [state.b, "B"]]) {
    if (!end) continue;
    const [px, py] = toCanvas(end.x);
    ctx.fillStyle = "#fff"; ctx.font = "bold 13px system-ui"; ctx.fillText(label, px + 7, py - 7);
  }
  drawAcquired(ctx);   // acquire.js: the photo's material, where it is a latent point
  state.drawnSlice = sliceKey();
  placeCursor();
}

// The current point's crosshair: an element over the map moved by a CSS transform (the compositor
// moves it; redrawing the map canvas per move cost the software rasteriser most of a drag's time).
function placeCursor() {
  if (!state.map || !state.x) return;
  const c = $("map"), [cx, cy] = toCanvas(state.x), k = mapBox().width / c.width;
  $("cursor").style.transform = `translate(${(cx * k).toFixed(1)}px, ${(cy * k).toFixed(1)}px)`;
  $("cursor").hidden = false;
}

// The map's box on the page, measured once per pointer press (or after a resize or scroll):
// measuring it on every move would make the browser lay the page out again within each move.
let mapRect = null;
function mapBox() { return mapRect || (mapRect = $("map").getBoundingClientRect()); }
function forgetMapBox() { mapRect = null; }

function bindMap() {
  const c = $("map"), tip = $("tooltip");
  let dragging = false, lastDown = null;
  const moved = new ResizeObserver(() => { forgetMapBox(); placeCursor(); });   // the map or the page above it changed size
  for (const el of [c, document.querySelector("header"), document.body]) if (el) moved.observe(el);
  window.addEventListener("scroll", forgetMapBox, { passive: true, capture: true });
  c.addEventListener("pointerenter", forgetMapBox);
  const pos = (ev) => {
    const r = mapBox();
    return [(ev.clientX - r.left) * c.width / r.width, (ev.clientY - r.top) * c.height / r.height, r];
  };
  // Near a measured material the point snaps to it. A click takes the material's whole point
  // (for q > 2 the map re-slices through it at once); while dragging, only the map's two
  // coordinates snap, so the point stays in the slice the map shows.
  const pick = (ev, whole) => {
    const [px, py] = pos(ev);
    const i = nearestPoint(px, py);
    let x = fromCanvas(px, py);
    if (i >= 0 && whole) x = state.info.latent[i].slice();
    else if (i >= 0) for (const d of state.dims) x[d] = state.info.latent[i][d];
    setX(x);
  };
  c.addEventListener("pointerdown", (ev) => {
    if (!state.map) return;
    forgetMapBox();   // measured again once for this press
    const now = performance.now();
    const again = lastDown && now - lastDown.t < 500 && Math.hypot(ev.clientX - lastDown.cx, ev.clientY - lastDown.cy) < 6;
    // the point before a press (before the first press of a double-click: where dblclick puts it back)
    lastDown = { x: again ? lastDown.x : state.x.slice(), t: now, cx: ev.clientX, cy: ev.clientY };
    dragging = state.dragging = true; c.setPointerCapture(ev.pointerId); pick(ev, true);
  });
  c.addEventListener("pointermove", (ev) => {
    if (!state.map) return;
    const [px, py, r] = pos(ev);
    const inside = ev.clientX >= r.left && ev.clientX < r.right && ev.clientY >= r.top && ev.clientY < r.bottom;
    const i = inside ? nearestPoint(px, py) : -1;   // captured outside the map: no tooltip
    if (i !== state.hover) { state.hover = i; drawMap(); }
    if (i >= 0) {
      tip.hidden = false; tip.innerHTML = thumbHtml(state.info.names[i], 48) + "<span>" + escapeHtml(state.info.names[i]) + "</span>";
      tip.style.left = (px * r.width / c.width + 12) + "px"; tip.style.top = (py * r.height / c.height - 10) + "px";
    } else tip.hidden = true;
    if (dragging) pick(ev, false);
  });
  // the tooltip names the material under a hovering pointer; a press's release (on the map or,
  // the pointer captured, anywhere else) takes it away until the pointer moves again
  const release = () => {
    tip.hidden = true;
    if (state.hover >= 0) { state.hover = -1; drawMap(); }
    if (!dragging) return;
    dragging = state.dragging = false;
    // the point's full answers (denoised frame, full table, ...) once the pointer has been up for REST
    // ms: a drag that starts again meanwhile never waits behind them (channel.pending() counts them)
    clearTimeout(state.restTimer);
    channel.owed += 1;
    state.restTimer = setTimeout(() => sendMove(true), REST);
    commitPoint();
  };
  c.addEventListener("pointerup", release);
  c.addEventListener("pointercancel", release);
  // wheel: zoom about the pointer (the map is rendered again for the new extent); double-click:
  // the whole map, and the point goes back to where it was before the double-click's first press
  c.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    if (!state.map) return;
    const [px, py] = pos(ev), [x0, x1, y0, y1] = state.map.extent;
    const f = Math.exp(Math.sign(ev.deltaY) * 0.18);
    const cx = x0 + px / c.width * (x1 - x0), cy = y0 + (1 - py / c.height) * (y1 - y0);
    state.zoom = [cx - (cx - x0) * f, cx + (x1 - cx) * f, cy - (cy - y0) * f, cy + (y1 - cy) * f];
    state.map = Object.assign({}, state.map, { extent: state.zoom });   // overlay follows at once
    drawMap(); requestMap();
  }, { passive: false });
  c.addEventListener("dblclick", () => {
    state.zoom = null;
    if (state.fullExtent) state.map = Object.assign({}, state.map, { extent: state.fullExtent });
    if (lastDown && !sameX(lastDown.x, state.x)) { setX(lastDown.x); commitPoint(); }
    requestMap(); drawMap();
  });
  c.addEventListener("pointerleave", () => { tip.hidden = true; if (state.hover >= 0) { state.hover = -1; drawMap(); } });
}

// q > 2: two axes for the map, a slider for every other coordinate
function buildSliceControls() {
  const q = state.info.q;
  if (q <= 2) return;
  $("slice-controls").hidden = false;
  for (const [k, sel] of [[0, $("dim0")], [1, $("dim1")]]) {
    for (let d = 0; d < q; d++) sel.add(new Option("x" + d, d));
    sel.value = state.dims[k];
    sel.onchange = () => {
      const d = [+$("dim0").value, +$("dim1").value];
      if (d[0] === d[1]) { sel.value = state.dims[k]; return; }
      state.dims = d; state.zoom = null; buildSliders(); requestMap();
    };
  }
  buildSliders();
}

function buildSliders() {
  const box = $("sliders");
  box.innerHTML = "";
  for (let d = 0; d < state.info.q; d++) {
    if (state.dims.includes(d)) continue;
    const [lo, hi] = coordRange(d);
    const row = document.createElement("div"); row.className = "row";
    row.innerHTML = `<label>x${d}</label><input type="range" data-dim="${d}" min="${lo}" max="${hi}" step="${(hi - lo) / 500}"><span class="end"></span>`;
    const input = row.querySelector("input");
    input.value = state.x[d];
    input.oninput = () => { const x = state.x.slice(); x[d] = +input.value; state.liveUntil = performance.now() + REST; setX(x); };
    input.onchange = commitPoint;
    box.appendChild(row);
  }
  updateSliders();
}

function updateSliders() {
  for (const input of document.querySelectorAll("#sliders input")) {
    const d = +input.dataset.dim;
    if (document.activeElement !== input) input.value = state.x[d];
    setText(input.nextElementSibling, fmtNum(state.x[d]));
  }
}

// ------------------------------------------------------------------ material panel
function materialName(x) {
  const i = state.info.latent.findIndex((p) => p.every((v, k) => v === x[k]));
  return i >= 0 ? state.info.names[i] : null;
}

function showMaterial(m) {
  update({ material: m });
  if (m.albedo) {
    const a = m.albedo;
    $("albedo-swatch").style.background = `rgb(${a.map((v) => Math.round(255 * Math.min(1, Math.max(0, v)) ** (1 / 2.2))).join(",")})`;
    const mean = (a[0] + a[1] + a[2]) / 3;
    $("albedo-val").textContent = `${colourWord(a)} · reflects ${(100 * mean).toFixed(0)}%`;
    $("albedo-detail").textContent = "albedo (bihemispherical), R G B: " + a.map((v) => v.toFixed(3)).join(" · ");
  }
  const rel = Math.min(1, m.variance / m.prior_variance);
  $("conf-bar").style.width = (100 * (1 - rel)).toFixed(1) + "%";
  $("conf-bar").style.background = rel > 0.5 ? "var(--neg)" : rel > 0.1 ? "var(--warn)" : "var(--accent)";
  $("variance-val").textContent = `GP variance ${fmtNum(m.variance, 4)} of ${fmtNum(m.prior_variance, 3)} (paper Eq. 2)`;
  const warn = [];
  if (rel > 0.5) warn.push("far from every measured material (GP variance near its prior): an extrapolation");
  if (m.albedo && m.albedo.some((v) => v < 0 || v > 1)) warn.push("albedo outside [0, 1]: not a physical material");
  if (m.negative_fraction !== undefined && m.negative_fraction > 1e-3)
    warn.push(`${(100 * m.negative_fraction).toFixed(1)}% of the table's bins are negative: a render clamps ` +
              "them to 0, the blend cannot (they differ here)");
  if (m.tables !== "ready") warn.push(m.tables_message);
  $("warnings").innerHTML = warn.map((w) => `<div class="warn">${escapeHtml(w)}</div>`).join("");
  $("nearest").innerHTML = "";
  if (m.measured) state.lastMeasured = m.measured;
  const near = m.measured || (m.live ? state.lastMeasured : null);   // a drag: the last one, marked stale
  const ratio = near ? near.distance / near.spacing : null;
  const how = ratio === null ? "" : ratio < 1e-6 ? "is the measured" : ratio < 0.5 ? "very close to" : ratio < 1.5 ? "close to" : "far from; nearest";
  $("measured").innerHTML = near ? `<span class="muted">${how}</span> ${thumbHtml(near.name, 18)}<b>${escapeHtml(near.name)}</b>` :
    `<span class="muted">${m.tables === "ready" ? "preparing the perceptual metric…" : escapeHtml(m.tables_message || "")}</span>`;
  $("measured-detail").textContent = near ? `perceptual distance to ${near.name}: ${fmtNum(near.distance)} ` +
    `(${fmtNum(ratio, 2)}× the median spacing of the measured materials)` : "";
  for (const n of m.nearest) {
    const b = document.createElement("button");
    b.innerHTML = thumbHtml(n.name, 16) + escapeHtml(n.name); b.title = `latent distance ${n.distance.toFixed(3)}`;
    b.onclick = () => { goTo(n.name); commitPoint(); };
    $("nearest").appendChild(b);
  }
  const max = Math.max(...m.weights.map((w) => Math.abs(w.w)), 1e-9);
  $("weights").innerHTML = "";
  for (const w of m.weights.filter((w) => Math.abs(w.w) > 5e-4)) {
    const half = 50 * Math.abs(w.w) / max;
    const name = document.createElement("div"); name.className = "name" + (w.kept ? " kept" : " pruned");
    name.textContent = w.name; name.onclick = () => { goTo(w.name); commitPoint(); };
    name.title = w.kept ? "kept: this material's image is in the blend" : "dropped by pruning (its share is spread over the kept ones)";
    const track = document.createElement("div"); track.className = "track";
    const bar = document.createElement("div"); bar.className = "bar" + (w.w < 0 ? " neg" : "") + (w.kept ? "" : " pruned");
    bar.style.left = (w.w < 0 ? 50 - half : 50) + "%"; bar.style.width = half + "%";
    track.appendChild(bar);
    const val = document.createElement("div"); val.className = "val"; val.textContent = w.w.toFixed(3);
    $("weights").append(name, track, val);
  }
  $("weights-note").textContent = `${m.n_kept} of ${state.info.names.length} kept after pruning (● kept, ○ dropped)` +
    (m.negative_weight > 1e-6 ? ` · negative weight ${m.negative_weight.toFixed(2)}` : "") +
    (m.pruning_albedo != null ? ` · albedo change ${(100 * m.pruning_albedo).toFixed(2)}%` +
      (m.pruning_albedo_budget != null ? ` (≤ ${(100 * m.pruning_albedo_budget).toFixed(2)}%)` : "") : "");
  $("weights-note").title = m.pruning || "";   // the bound pruning reached (albedo, cosine-weighted, raw L2)
}

// A colour's name for people: hue and lightness of the albedo (linear RGB).
function colourWord(a) {
  const [r, g, b] = a.map((v) => Math.max(0, v)), max = Math.max(r, g, b), min = Math.min(r, g, b);
  const light = (r + g + b) / 3, tone = light < 0.05 ? "black" : light < 0.2 ? "dark" : light < 0.5 ? "mid" : "light";
  if (max - min < 0.15 * max || max <= 0) return tone === "black" ? "black" : tone === "light" && light > 0.7 ? "white" : tone + " grey";
  let h = 0;
  if (max === r) h = ((g - b) / (max - min) + 6) % 6; else if (max === g) h = (b - r) / (max - min) + 2; else h = (r - g) / (max - min) + 4;
  const hue = ["red", "orange", "yellow", "yellow-green", "green", "teal", "cyan", "blue", "blue", "violet", "magenta", "pink"][Math.floor(h * 2) % 12];
  return (tone === "mid" ? "" : tone + " ") + hue;
}

// Gloss of the preview table: log10 of the reflectance towards the mirror direction (theta_h = 0)
// over that at theta_h = 60 degrees, both at theta_d = 10 degrees (mean RGB), in words.
function glossOf() {
  if (!preview || !preview.table) return null;
  const { dims, full_dims: full, strides } = preview.table.layout;
  const bin = (deg, k, sqrtMap) => Math.min(dims[k] - 1, Math.max(0, Math.round(((sqrtMap ? Math.sqrt(deg / 90) : deg / 90) * full[k] - 0.5) / strides[k])));
  const mean = (v) => (v[0] + v[1] + v[2]) / 3, id = bin(10, 1, false);
  const peak = mean(preview.value(0, id, 0)), wide = mean(preview.value(bin(60, 0, true), id, 0));
  if (!(peak > 0) || !(wide >= 0)) return null;
  const g = Math.log10(peak / Math.max(wide, 1e-6));
  const word = g < 0.3 ? "matte" : g < 1 ? "satin" : g < 2 ? "glossy" : g < 3 ? "very glossy" : "mirror-like";
  return { g, word, peak, wide };
}
function showGloss() {
  const gl = glossOf();
  setText($("gloss-val"), gl ? gl.word : "");
  $("gloss-bar").style.width = gl ? (100 * Math.min(1, Math.max(0.03, gl.g / 4))).toFixed(0) + "%" : "0";
  setText($("gloss-detail"), gl ? `gloss: mirror-direction reflectance ${fmtNum(gl.peak)} /sr, 60° away ${fmtNum(gl.wide)} /sr ` +
    `(10^${gl.g.toFixed(2)}×)` : "");
}

function escapeHtml(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]); }

function goTo(name) { setX(state.info.latent[state.info.names.indexOf(name)]); }

// ------------------------------------------------------------------ snippets
function showSnippet(sn) {
  if (sn.folder !== state.snippetFolder) return;   // asked for before the folder changed
  $("snippet").textContent = sn.xml;
  $("snippet").dataset.x = sn.x.join(",");
  update({ snippet: sn });
  for (const w of snippetWaiters.splice(0)) w();
}
const snippetWaiters = [];
// The snippet of the point shown: the one at hand when it is for state.x, else asked for now.
async function currentSnippet() {
  while (!state.snippet || !sameX(state.snippet.x, state.x)) {
    const seq = channel.send({ type: "snippet", x: state.x, folder: state.snippetFolder }, ["snippet"]);
    await new Promise((resolve) => { snippetWaiters.push(resolve); setTimeout(resolve, 5000); });
    if (channel.isCurrent("snippet", seq) && !(state.snippet && sameX(state.snippet.x, state.x))) {
      throw new Error("no snippet for the current point from the server");
    }
  }
  return state.snippet;
}
async function copySnippet(which, what) {
  try { const sn = await currentSnippet(); copy(sn[which], what); clearError("snippet"); }
  catch (e) { setStatus("snippet: " + e.message, true, "snippet"); }
}
async function copy(text, what) {
  state.copied = text;
  try { await navigator.clipboard.writeText(text); $("copied").textContent = what + " copied"; }
  catch (e) {
    const ta = document.createElement("textarea"); ta.value = text; document.body.appendChild(ta); ta.select();
    document.execCommand("copy"); ta.remove(); $("copied").textContent = what + " copied";
  }
  setTimeout(() => { $("copied").textContent = ""; }, 2000);
}

// ------------------------------------------------------------------ paths
// The scrubber follows Manifold.path(a, b, steps, kind) (manifold/paths.py): the straight segment
// at once; uniform and geodesic are computed by the server in the background (seconds) and
// replace it when they arrive, cached there per pair. t moves along the path's points at equal
// index steps (equal perceptual steps for uniform and geodesic).
const ROUTE_STEPS = 21;
function endLabel(end) { return end ? end.name || "(" + end.x.map((v) => fmtNum(v)).join(", ") + ")" : "–"; }
const pathReady = () => !!(state.a && state.b && !sameX(state.a.x, state.b.x));
// The path's part of the page, drawn from the state (store.js): the ends, what the path is
// (state.route.note) and the controls that need two different ends; the map shows the path.
function drawPath() {
  setText($("a-label"), endLabel(state.a));
  setText($("b-label"), endLabel(state.b));
  $("scrub").disabled = !pathReady(); $("export-path").disabled = !pathReady();
  setText($("route-state"), state.route ? state.route.note : "");
  $("route-cancel").hidden = !(state.route && state.route.computing);
  drawMap();
}
view(["a", "b", "route"], drawPath);
function setEnd(which) {
  $("scrub").value = which === "a" ? 0 : 1000; updateScrub();
  update({ [which]: { x: state.x.slice(), name: materialName(state.x) }, route: null });
  if (pathReady()) requestRoute();
}
function straightRoute() {
  const a = state.a.x, b = state.b.x;
  return Array.from({ length: ROUTE_STEPS }, (_, k) => a.map((v, d) => v + (k / (ROUTE_STEPS - 1)) * (b[d] - v)));
}
function requestRoute() {
  const kind = $("path-kind").value, straight = kind === "straight";
  if (!straight) state.routeSeq = channel.send({ type: "route", a: state.a.x, b: state.b.x, steps: ROUTE_STEPS, kind }, ["route"]);
  update({ route: { kind: "straight", want: kind, a: state.a.x, b: state.b.x, points: straightRoute(), computing: !straight,
                    note: straight ? "the latent segment" : `${kind}: computing in the background… (straight meanwhile)` } });
}
// The server's progress of the path being computed (every half second): time and steps so far.
function routeProgress(meta) {
  const r = state.route;
  if (!r || !r.computing || meta.route_seq !== state.routeSeq) return;
  update({ route: Object.assign({}, r, { note: `${r.want}: computing… ${meta.seconds.toFixed(0)} s, ` +
    `${meta.evaluations} evaluations of the metric (straight meanwhile)` }) });
}
function cancelRoute() {   // the path stops at its next step; the route's error answer says so
  if (state.route && state.route.computing) channel.send({ type: "cancel", kind: "route" }, []);
}
function showRoute(meta) {
  const r = state.route;
  if (!r || meta.seq !== state.routeSeq || meta.kind !== r.want || !sameX(meta.a, r.a) || !sameX(meta.b, r.b)) return;
  const onPath = sameX(state.x, pointOnRoute(+$("scrub").value / 1000));
  const L = meta.lengths.reduce((s, v) => s + v, 0), spread = Math.max(...meta.lengths) / (L / meta.lengths.length);
  update({ route: Object.assign({}, r, { kind: meta.kind, points: meta.points, computing: false,
    note: `${meta.kind} · perceptual length ${fmtNum(L)} · largest step ${spread.toFixed(2)}× the mean` }) });
  if (onPath) { scrub(); commitPoint(); }   // the point shown moves onto the new path
}
function routeFailed(meta) {
  if (meta.seq !== state.routeSeq || !state.route) return;
  update({ route: Object.assign({}, state.route, { computing: false,
    note: `${state.route.want} unavailable (${meta.error}): straight` }) });
}
function pointOnRoute(t) {
  const P = state.route.points, u = t * (P.length - 1), k = Math.min(P.length - 2, Math.floor(u)), f = u - k;
  if (f === 0) return P[k].slice();
  if (k === P.length - 2 && f === 1) return P[k + 1].slice();
  return P[k].map((v, d) => (1 - f) * v + f * P[k + 1][d]);
}
function drawRoute(ctx) {
  const [ax, ay] = toCanvas(state.a.x), [bx, by] = toCanvas(state.b.x), r = state.route;
  ctx.strokeStyle = r && r.kind !== "straight" ? "rgba(255,255,255,.35)" : "rgba(255,255,255,.85)";
  ctx.setLineDash([6, 4]); ctx.lineWidth = 1.5;
  ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke(); ctx.setLineDash([]);
  if (!r || r.kind === "straight") return;
  ctx.strokeStyle = "#ffd166"; ctx.lineWidth = 2.5; ctx.beginPath();
  r.points.forEach((p, k) => { const [x, y] = toCanvas(p); if (k) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  ctx.stroke();
  ctx.fillStyle = "#ffd166";
  for (const p of r.points) { const [x, y] = toCanvas(p); ctx.beginPath(); ctx.arc(x, y, 2, 0, 2 * Math.PI); ctx.fill(); }
}
function updateScrub() { $("scrub-t").textContent = "t = " + (+$("scrub").value / 1000).toFixed(2); }
function scrub() {
  updateScrub();
  state.liveUntil = performance.now() + REST;
  setX(pointOnRoute(+$("scrub").value / 1000));
}
function exportPath() {
  state.pathSeq = channel.send({ type: "path", basis: state.basis, steps: $("steps").value, kind: $("path-kind").value,
    a: state.a.name || state.a.x, b: state.b.name || state.b.x }, ["path"]);
  $("path-cmd").classList.add("stale");
}
function showPath(meta) {
  if (meta.seq !== state.pathSeq) return;   // for ends or steps changed since
  clearError("path");
  $("path-cmd").hidden = false; $("path-cmd").classList.remove("stale");
  $("path-cmd").textContent = meta.command; copy(meta.command, "command");
}

// ------------------------------------------------------------------ plots and tabs
function drawPlots() {
  const tab = state.tab || "weights";
  if (tab === "slice" && drawSlice(preview, $("slice"), +$("phi-d").value)) {
    $("slice-hi").textContent = SLICE_RANGE[1].toFixed(0); $("slice-lo").textContent = SLICE_RANGE[0].toFixed(0);
  }
  if (tab === "lobe") state.lobePeak = drawLobe(preview, $("lobe"), +$("theta-i").value);
}
function bindTabs() {
  for (const b of document.querySelectorAll(".tabs button")) {
    b.onclick = () => {
      state.tab = b.dataset.tab;
      for (const o of document.querySelectorAll(".tabs button")) o.classList.toggle("on", o === b);
      for (const t of ["weights", "slice", "lobe"]) $("tab-" + t).hidden = t !== state.tab;
      drawPlots();
    };
  }
  $("phi-d").oninput = () => { $("phi-d-val").textContent = $("phi-d").value + "°"; drawPlots(); };
  $("theta-i").oninput = () => { $("theta-i-val").textContent = $("theta-i").value + "°"; drawPlots(); };
  $("env-rot").oninput = () => preview && preview.setRotation(+$("env-rot").value * Math.PI / 180);
  $("key-power").oninput = () => preview && preview.setKeyPower(+$("key-power").value * Math.PI);
  $("lighting").onchange = async () => {
    if (!preview) return;
    const msg = await preview.setLighting($("lighting").value, state.basis);
    if (msg) { setStatus("sphere light: " + msg, true, "lighting"); $("lighting").value = "studio"; preview.setLighting("studio"); }
    else clearError("lighting");
  };
}

// ------------------------------------------------------------------ reference
// state.reference: null (none asked for in this page), or the job's id and its state ("starting",
// "queued", "rendering", "done", "cancelled", "failed"), progress, message, and, when done, the
// job's answer and the exposure its images were asked at. drawReference shows it.
async function startReference() {
  update({ reference: { state: "starting", progress: 0, message: "starting" } });
  try {
    const job = await (await api("/api/reference", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ basis: state.basis, x: state.x, spp: +$("ref-spp").value, tab: TAB }) })).json();
    state.referenceJob = job.id;
    update({ reference: { id: job.id, state: "queued", progress: 0, message: "waiting…" } });
    pollReference(job.id);
  } catch (e) { update({ reference: null }); setStatus("reference: " + e.message, true, "reference"); }
}
async function pollReference(id) {
  let job;
  try { job = await (await api("/api/reference/" + id)).json(); }
  catch (e) { update({ reference: null }); setStatus("reference: " + e.message, true, "reference"); return; }
  const r = { id, state: job.state, progress: job.progress, message: job.state === "queued" ? "waiting…" : job.message || "starting" };
  if (job.state === "queued" || job.state === "rendering") { update({ reference: r }); setTimeout(() => pollReference(id), 400); return; }
  if (job.state === "failed") { update({ reference: null }); setStatus("reference failed: " + job.message, true, "reference"); return; }
  if (job.state === "done") { r.job = job; r.exposure = state.exposure; clearError("reference"); }
  update({ reference: r });
}
function cancelReference() {
  const r = state.reference;
  if (r && r.id) api(`/api/reference/${r.id}/cancel`, { method: "POST" }).catch(() => {});
}
function drawReference() {   // a view of store.js: the reference box from state.reference
  const r = state.reference, b = state.info.bases.find((b) => b.name === state.basis);
  const running = !!r && ["starting", "queued", "rendering"].includes(r.state), bar = $("ref-progress");
  $("ref-start").disabled = running || !b.scene_available;
  $("ref-note").hidden = b.scene_available;
  $("ref-cancel").hidden = !running || !r.id;
  bar.hidden = !running;
  if (running) {
    bar.firstElementChild.style.width = (100 * r.progress).toFixed(0) + "%";
    setText(bar.lastElementChild, r.message);
  }
  $("ref-note-cancel").hidden = !(r && r.state === "cancelled");
  if (r && r.state === "cancelled") setText($("ref-note-cancel"), "reference " + r.message);
  const job = r && r.state === "done" ? r.job : null;
  $("ref-result").hidden = !job;
  if (!job || $("ref-result").dataset.job === String(r.id)) return;
  $("ref-result").dataset.job = r.id;
  const ev = "?exposure=" + r.exposure;
  $("ref-blend").src = `/api/reference/${r.id}/blend.png${ev}`;
  $("ref-ref").src = `/api/reference/${r.id}/reference.png${ev}`;
  $("ref-err").src = `/api/reference/${r.id}/error.png`;
  $("ref-caption").textContent = `reference (full GI, ${job.spp} spp, ${job.seconds.toFixed(1)} s)`;
  const e = job.error;
  // A noisy reference differs from an exact blend by its own noise: judge the rest of the error.
  const verdict = e.agrees === true ? `the blend agrees with full GI within the reference's ${job.spp}-spp noise`
    : e.psnr >= 40 ? "the blend is indistinguishable from full GI" : e.psnr >= 30 ? "the blend is close to full GI"
    : e.agrees === false ? "the blend differs from full GI by more than the reference's noise (its own noise included)"
    : "the blend differs visibly from full GI";
  const noise = e.noise_rel_mse == null ? "" : ` · the reference's noise ${fmtNum(e.noise_rel_mse, 4)} · beyond it (the blend's bias and noise) ${fmtNum(e.excess_rel_mse, 4)}`;
  $("ref-metrics").innerHTML = `PSNR ${e.psnr.toFixed(1)} dB: ${verdict}<details><summary>details</summary>` +
    escapeHtml(`rel. MSE ${fmtNum(e.rel_mse, 4)}${noise} · mean |Δ| ${fmtNum(e.mean_abs, 4)} · at x = (${job.x.map((v) => fmtNum(v)).join(", ")})`) +
    `</details>`;
}
view(["reference"], drawReference);

// ------------------------------------------------------------------ start
async function main() {
  try { state.info = await (await api("/api/info")).json(); }
  catch (e) { setStatus("cannot reach the server: " + e.message, true, "connection"); return; }
  const info = state.info;
  for (const b of info.bases) $("basis").add(new Option(`${b.name} (${b.resolution.join("×")}, ${b.images} materials)`, b.name));
  state.basis = info.bases[0].name;
  $("basis").onchange = () => {
    state.basis = $("basis").value; sceneInfo(); requestAll();
    if ($("lighting").value === "scene") $("lighting").onchange();   // the new scene's light
  };
  sceneInfo();
  preview = new MaterialPreview($("sphere"), $("sphere-msg"));
  channel = new Channel(onMessage, () => state.x && reconnected());
  // start at the measured material closest to the centre of the data
  const mean = info.latent[0].map((_, k) => info.latent.reduce((s, p) => s + p[k], 0) / info.latent.length);
  let best = 0, bd = Infinity;
  info.latent.forEach((p, i) => { const d = p.reduce((s, v, k) => s + (v - mean[k]) ** 2, 0); if (d < bd) { bd = d; best = i; } });
  let x = info.latent[best].slice();
  const hash = new URLSearchParams(location.hash.slice(1));   // #x=...&basis=... from a link
  if (hash.get("basis") && info.bases.some((b) => b.name === hash.get("basis"))) {
    state.basis = hash.get("basis"); $("basis").value = state.basis; sceneInfo();
  }
  if (hash.get("x")) x = linkedPoint(hash.get("x")) || x;
  state.x = x;   // the sliders are built at it; setX draws every part
  buildSliceControls();
  bindMap();
  state.x = null;
  setX(x);
  $("exposure").oninput = () => {
    state.exposure = +$("exposure").value;
    $("exposure-val").textContent = state.exposure.toFixed(1) + " EV";
    preview && preview.setExposure(state.exposure);
    updateSavePng();
    if (!reexposeRefined()) requestFrame();
  };
  for (const n of [...info.names].sort()) $("material-names").appendChild(new Option(n));
  $("search").oninput = () => {   // search by name: a full name (typed or picked from the list) goes there
    const v = $("search").value.trim(), hit = info.names.find((n) => n.toLowerCase() === v.toLowerCase());
    $("search").setCustomValidity("");
    if (hit) { goTo(hit); commitPoint(); $("search").blur(); }   // a point elsewhere: the filter ends
    else update({ filter: v.toLowerCase() });   // the gallery shows the names matching what is typed
  };
  $("search").onkeydown = (ev) => {   // Enter: the one name containing what is typed, else say why not
    if (ev.key !== "Enter") return;
    const v = $("search").value.trim().toLowerCase(), some = info.names.filter((n) => n.toLowerCase().includes(v));
    if (v && some.length === 1) { $("search").value = some[0]; $("search").oninput(); return; }
    $("search").setCustomValidity(some.length ? `${some.length} materials contain "${v}": pick one from the list`
                                              : `no measured material's name contains "${v}"`);
    $("search").reportValidity();
  };
  $("set-a").onclick = () => setEnd("a");
  $("set-b").onclick = () => setEnd("b");
  $("scrub").oninput = scrub;
  $("scrub").onchange = commitPoint;
  for (const k of info.path_kinds) $("path-kind").add(new Option(k, k));
  $("path-kind").value = info.path_kind;
  $("path-kind").onchange = () => {
    if (!pathReady()) return;
    const onPath = state.route && sameX(state.x, pointOnRoute(+$("scrub").value / 1000));
    requestRoute();
    if (onPath) { scrub(); commitPoint(); }   // the point follows the scrubber onto the new path
  };
  bindTabs();
  bindShelf();
  bindAcquire();
  window.addEventListener("resize", () => { forgetMapBox(); placeCursor(); });
  $("export-path").onclick = exportPath;
  $("route-cancel").onclick = cancelRoute;
  $("ref-start").onclick = startReference;
  $("ref-cancel").onclick = cancelReference;
  $("refine-auto").onchange = () => { if ($("refine-auto").checked) refineHere(); else refineOff(); };
  $("refine-show").onclick = () => state.refine && state.refine.offer && state.refine.offer.show();
  if (!info.refine_spp) { $("refine-auto").checked = false; $("refine-auto").closest(".row").hidden = true; }
  else {   // refine.js: the server's --refine-spp is the default
    const sel = $("refine-spp"), spp = String(info.refine_spp);
    if (![...sel.options].some((o) => o.value === spp)) sel.add(new Option(spp, spp));
    sel.value = spp;
  }
  state.snippetFolder = info.snippet_folder;
  $("snippet-folder").value = info.snippet_folder;
  $("snippet-folder").onchange = () => {   // the snippets of the point again, relative to the new folder
    state.snippetFolder = $("snippet-folder").value.trim();
    delete asked.snippet; update({ snippet: null }); scheduleMove();
  };
  $("copy-xml").onclick = () => copySnippet("xml", "XML");
  $("copy-py").onclick = () => copySnippet("python", "Python");
  if (info.tables === "loading") pollTables();
}

// The point of a shared link (#x=a,b,...: numbers, or a material's name). A point outside the
// latent data's range (that of the sliders) is clamped into it; anything else is refused.
// Either way the page says so and stays usable.
function linkedPoint(text) {
  const { q, names, latent } = state.info;
  if (names.includes(text)) return latent[names.indexOf(text)].slice();
  const parts = text.split(",");
  if (parts.length !== q || !parts.every((p) => NUMBER.test(p.trim()))) {
    setStatus(`the link's point x=${text.slice(0, 60)} is not ${q} numbers nor a material name: ignored`, true, "link");
    return null;
  }
  const x = parts.map(Number), clamped = x.map((v, k) => { const [lo, hi] = coordRange(k); return Math.min(hi, Math.max(lo, v)); });
  if (!sameX(x, clamped)) setStatus(`the link's point x=${text.slice(0, 60)} is outside the latent space shown: moved inside`, true, "link");
  return clamped;
}
function coordRange(k) {
  const vals = state.info.latent.map((p) => p[k]), lo = Math.min(...vals), hi = Math.max(...vals), pad = 0.25 * (hi - lo || 1);
  return [lo - pad, hi + pad];
}

function sceneInfo() {
  const b = state.info.bases.find((b) => b.name === state.basis);
  $("scene-info").textContent = `${b.scene.split("/").pop()} · ${b.resolution.join("×")} · ${b.spp} spp basis`;
  drawReference();
  drawAcquire();
}

let tablesPoll = 0;
async function pollTables() {   // one poll at a time; a failed one (the server away) is tried again
  const run = ++tablesPoll;
  let info;
  try { info = await (await api("/api/info")).json(); }
  catch (e) { setTimeout(() => run === tablesPoll && pollTables(), 1000); return; }
  if (run !== tablesPoll) return;
  state.info.tables = info.tables;
  if (info.tables === "loading") { setTimeout(() => run === tablesPoll && pollTables(), 250); return; }
  requestAll();
}

window.explore = { state, update, setStatus, setX, setEnd, currentSnippet, commitPoint, stepHistory, pointOnRoute, drawPlots, get channel() { return channel; }, get preview() { return preview; } };
main();
