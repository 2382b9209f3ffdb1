// Refinement on release (issue 21): where a drag ends (or a point is chosen), the server renders
// what the basis cannot give at that point (its L2+ light; blend.py --refine) in passes, and the
// scene view shows each pass's exact full-GI estimate, with the noise the passes measure, until the
// point moves again. Uses app.js's state, $, api, sameX and fmtNum.
"use strict";

let refineRun = 0;

function refineAvailable() {
  const box = $("refine-auto");
  return box && box.checked && state.x && state.basis && !state.dragging && $("ref-note").hidden;
}

async function refineHere() {
  if (!refineAvailable()) return;
  const x = state.x.slice(), run = ++refineRun, status = $("refine-status");
  const current = () => run === refineRun && sameX(x, state.x) && !state.dragging;
  status.textContent = "refining…";
  let job;
  try {
    job = await (await api("/api/reference", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ basis: state.basis, x, spp: +$("refine-spp").value, kind: "refine" }) })).json();
  } catch (e) { if (current()) status.textContent = "refine: " + e.message; return; }
  let shown = -1;
  while (current()) {
    try { job = await (await api("/api/reference/" + job.id)).json(); }
    catch (e) { if (current()) status.textContent = "refine: " + e.message; return; }
    if (!current()) return;
    if (job.state === "failed") { status.textContent = "refine failed: " + job.message; return; }
    if (job.images.includes("refined") && job.progress > shown) {
      shown = job.progress;
      const img = new Image();
      img.src = `/api/reference/${job.id}/refined.png?exposure=${state.exposure}`;
      try { await img.decode(); } catch (e) { return; }
      if (!current()) return;
      $("scene").getContext("2d").drawImage(img, 0, 0);
      state.refined = { x, exposure: state.exposure, job: job.id };
      $("scene").dataset.refined = job.id;
      const n = job.error && job.error.noise_rel_mse;
      status.textContent = `refined: exact full GI (${job.message})` +
        (n != null ? ` · its noise, rel. MSE ${fmtNum(n, 3)}` : "");
    }
    if (job.state === "done") return;
    await new Promise((r) => setTimeout(r, 300));
  }
}

// Whether a frame from the server would replace the refined image of the same point (it keeps it).
function keepsRefined(meta) {
  const r = state.refined;
  if (r && sameX(meta.x, r.x) && meta.exposure === r.exposure && sameX(r.x, state.x)) return true;
  if (r) { state.refined = null; delete $("scene").dataset.refined; $("refine-status").textContent = ""; }
  return false;
}
