// What an artist keeps at hand, all in the page: undo/redo of point moves (Ctrl-Z,
// Ctrl-Shift-Z), favourites (this browser's localStorage), up to four points compared side by
// side, and the measured materials as thumbnails (the server's sheet, /api/thumbs.png).
"use strict";

// ------------------------------------------------------------------ undo / redo
// A move is committed when it ends (pointer up, a click, a name, a slider let go); undo goes
// back to the point before it. Moves made by undo/redo are not committed again.
const undoLog = { past: [], future: [], at: null, limit: 200 };

function commitPoint() {
  const x = state.x;
  if (!x) return;
  if (undoLog.at && !sameX(undoLog.at, x)) {
    undoLog.past.push(undoLog.at);
    if (undoLog.past.length > undoLog.limit) undoLog.past.shift();
    undoLog.future = [];
  }
  undoLog.at = x.slice();
  updateHistoryButtons();
  clearError("link");   // a point of the user's own: the link's message is answered
  refineHere();   // refine.js
}
function stepHistory(back) {
  const from = back ? undoLog.past : undoLog.future, to = back ? undoLog.future : undoLog.past;
  if (!from.length) return;
  to.push(undoLog.at);
  undoLog.at = from.pop();
  setX(undoLog.at);
  updateHistoryButtons();
}
function updateHistoryButtons() {
  $("undo").disabled = !undoLog.past.length;
  $("redo").disabled = !undoLog.future.length;
}
function bindHistory() {
  $("undo").onclick = () => stepHistory(true);
  $("redo").onclick = () => stepHistory(false);
  document.addEventListener("keydown", (ev) => {
    const typing = ev.target.matches && ev.target.matches("input[type=text], input:not([type]), textarea, input[list]");
    if (typing || !(ev.ctrlKey || ev.metaKey)) return;
    const k = ev.key.toLowerCase();
    if (k === "z" || k === "y") { ev.preventDefault(); stepHistory(k === "z" && !ev.shiftKey); }
  });
}

// ------------------------------------------------------------------ thumbnails
function thumbStyle(i, px) {
  const t = state.thumbs;
  if (!t || i < 0) return "";
  const c = i % t.columns, r = Math.floor(i / t.columns), rows = Math.ceil(state.info.names.length / t.columns);
  return `background-image:url(${t.url});background-size:${t.columns * px}px ${rows * px}px;` +
         `background-position:${-c * px}px ${-r * px}px`;
}
function thumbHtml(name, px = 20) {
  const i = state.info.names.indexOf(name);
  return state.thumbs && i >= 0 ? `<i class="thumb" style="width:${px}px;height:${px}px;${thumbStyle(i, px)}"></i>` : "";
}
async function pollThumbs() {
  const t = state.info.thumbs;
  if (!t) { $("thumbs-state").textContent = "(no thumbnails: --no-thumbnails)"; buildGallery(); return; }
  if (t.state === "rendering") {
    $("thumbs-state").textContent = "rendering thumbnails in the background…";
    setTimeout(async () => {
      try { state.info.thumbs = (await (await api("/api/info")).json()).thumbs; } catch (e) { /* retried */ }
      pollThumbs();
    }, 2000);
    buildGallery();
    return;
  }
  if (t.state === "ready") {
    state.thumbs = { url: "/api/thumbs.png", columns: t.columns, size: t.size };
    const img = new Image();   // the map draws each measured material as its thumbnail
    img.onload = () => { state.thumbImage = img; drawMap(); };
    img.src = state.thumbs.url;
  }
  $("thumbs-state").textContent = t.state === "ready" ? "rendered with the plugin" : t.message;
  buildGallery();
  if (state.material) showMaterial(state.material);
}
// The highlights that follow the point and the lists (a view of store.js): the entry of the
// compare and favourite lists at the point and the favourite button.
function renderHighlights() {
  const here = (el) => el.dataset.x && sameX(el.dataset.x.split(",").map(Number), state.x);
  for (const el of document.querySelectorAll("#compare .cmp, #favs .fav")) el.classList.toggle("here", here(el));
  setText($("fav"), state.favs.some((f) => sameX(f.x, state.x)) ? "★ favourite" : "☆ favourite");
}
// The search box (a view of store.js): its text is the point's name; what is typed filters the
// gallery (state.filter) until the point moves.
function renderSearch() {
  const name = materialName(state.x) || "", search = $("search");
  if (search.value !== name) { search.value = name; search.setCustomValidity(""); }
}
function buildGallery() {
  const box = $("gallery"), filter = state.filter || "";
  box.innerHTML = "";
  let shown = 0;
  state.info.names.forEach((name, i) => {
    if (filter && !name.toLowerCase().includes(filter)) return;
    shown++;
    const b = document.createElement("button");
    b.className = "tile"; b.title = name; b.dataset.name = name;
    b.innerHTML = (state.thumbs ? `<i class="thumb" style="width:44px;height:44px;${thumbStyle(i, 44)}"></i>` : "") +
                  `<span>${escapeHtml(name)}</span>`;
    b.onclick = () => { goTo(name); commitPoint(); };
    box.appendChild(b);
  });
  const n = state.info.names.length;
  setText($("gallery-count"), filter ? `${shown} of ${n} match “${filter}”` : `${n} materials`);
}

// ------------------------------------------------------------------ favourites
// state.favs (this browser's localStorage keeps them per manifold); changed only by setFavs.
const favKey = () => "mitsuba-manifold-explore-favourites:" + state.info.manifold;
function loadFavs() {
  try { return JSON.parse(localStorage.getItem(favKey())) || []; } catch (e) { return []; }
}
function setFavs(favs) {
  favs = favs.slice(0, 24);
  try { localStorage.setItem(favKey(), JSON.stringify(favs)); } catch (e) { /* full: kept for this tab */ }
  update({ favs });
}
function pointLabel(x) { return materialName(x) || "(" + x.map((v) => fmtNum(v)).join(", ") + ")"; }
function addFavourite() {
  setFavs([{ x: state.x.slice(), label: pointLabel(state.x), img: preview && preview.snapshot() }]
    .concat(state.favs.filter((f) => !sameX(f.x, state.x))));
}
function showFavs() {   // a view of store.js: the list of state.favs
  const box = $("favs"), favs = state.favs;
  box.innerHTML = favs.length ? "" : `<span class="muted small">☆ favourite keeps the current point here</span>`;
  favs.forEach((f, k) => {
    const item = document.createElement("div");
    item.className = "fav" + (sameX(f.x, state.x) ? " here" : "");
    item.dataset.x = f.x.join(",");
    item.title = f.label;
    item.innerHTML = (f.img ? `<img src="${f.img}" alt="">` : thumbHtml(f.label, 40)) +
                     `<span>${escapeHtml(f.label)}</span><button class="x" title="remove">×</button>`;
    item.onclick = (ev) => {
      if (ev.target.classList.contains("x")) { setFavs(state.favs.filter((_, j) => j !== k)); return; }
      setX(f.x); commitPoint();
    };
    box.appendChild(item);
  });
}

// ------------------------------------------------------------------ compare
// state.compare, each slot: the scene frame of its point (PNG from the server), the sphere as
// drawn when it was added, its name or coordinates and the closest measured material.
const COMPARE_MAX = 4;
function addCompare() {
  if (state.compare.some((c) => sameX(c.x, state.x))) return;
  update({ compare: state.compare.slice(-(COMPARE_MAX - 1)).concat([{ x: state.x.slice(), label: pointLabel(state.x),
    img: preview && preview.snapshot(),
    measured: state.material && sameX(state.material.x, state.x) ? state.material.measured : null }]) });
}
function showCompare() {   // a view of store.js: the list of state.compare
  const box = $("compare"), items = state.compare;
  box.innerHTML = items.length ? "" : `<span class="muted small">+ compare adds the current point (2 to 4 side by side)</span>`;
  box.style.gridTemplateColumns = `repeat(${Math.max(2, items.length)}, minmax(0, 1fr))`;
  items.forEach((c, k) => {
    const q = new URLSearchParams({ x: c.x.join(","), basis: state.basis, exposure: state.exposure, format: "png" });
    const cell = document.createElement("figure");
    cell.className = "cmp" + (sameX(c.x, state.x) ? " here" : "");
    cell.dataset.x = c.x.join(",");
    cell.innerHTML = `<div class="pair"><img class="frame" src="/api/frame?${q}" alt="scene">` +
      (c.img ? `<img class="ball" src="${c.img}" alt="sphere">` : "") + `</div>` +
      `<figcaption>${escapeHtml(c.label)}${c.measured && c.measured.name !== c.label ?
        ` · closest ${escapeHtml(c.measured.name)} (d ${fmtNum(c.measured.distance)})` : ""}` +
      `<button class="x" title="remove">×</button></figcaption>`;
    cell.onclick = (ev) => {
      if (ev.target.classList.contains("x")) { update({ compare: state.compare.filter((_, j) => j !== k) }); return; }
      setX(c.x); commitPoint();
    };
    box.appendChild(cell);
  });
}
view(["favs"], showFavs);
view(["compare"], showCompare);
view(["x", "favs", "compare"], renderHighlights);
view(["x"], renderSearch);

function bindShelf() {
  bindHistory();
  $("fav").onclick = addFavourite;
  $("compare-add").onclick = addCompare;
  undoLog.at = state.x.slice();
  update({ favs: loadFavs() });
  showCompare(); pollThumbs();
}
