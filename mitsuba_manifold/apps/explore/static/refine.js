// Refinement on release (issue 21): where a drag ends (or a point is chosen), the server renders
// what the basis cannot give at that point (its L2+ light; blend.py --refine) in passes. After each
// pass from the second on, the server says whether the blend shown agrees with that unbiased
// estimate within its measured noise: where it does, the blend stays (it is the less noisy image)
// and the status says so; where it does not, the scene view shows the refined image until the
// point, the basis or the exposure changes. Uses app.js's state, $, api, sameX and fmtNum.
"use strict";

let refineRun = 0;

function refineAvailable() {
  const box = $("refine-auto");
  return box && box.checked && state.x && state.basis && !state.dragging && $("ref-note").hidden;
}

async function refineHere() {
  if (!refineAvailable()) return;
  const x = state.x.slice(), basis = state.basis, run = ++refineRun, status = $("refine-status");
  const current = () => run === refineRun && sameX(x, state.x) && state.basis === basis && !state.dragging;
  const say = (text) => { if (current()) status.textContent = text; };
  say("refining…");
  try {
    let job = await (await api("/api/reference", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ basis, x, spp: +$("refine-spp").value, kind: "refine" }) })).json();
    let seen = -1;
    while (current()) {
      job = await (await api("/api/reference/" + job.id)).json();
      if (!current()) break;
      if (job.state === "failed") { say("refine failed: " + job.message); return; }
      const e = job.error || {};
      if (job.progress > seen && e.agrees != null) {
        seen = job.progress;
        if (e.agrees) {
          say(`full GI checked (${job.message}): the blend agrees with the unbiased render within its noise ` +
              `(rel. MSE ${fmtNum(e.blend_rel_mse, 3)}, noise ${fmtNum(e.noise_rel_mse, 3)})`);
        } else if (await showRefined(job, x, basis, current)) {
          say(`refined (${job.message}): unbiased full GI, noise rel. MSE ${fmtNum(e.noise_rel_mse, 3)}; ` +
              `the blend differed by ${fmtNum(e.blend_rel_mse, 3)}`);
        }
      } else if (e.agrees == null) say(`refining… ${job.message}`);
      if (job.state === "done") return;
      await new Promise((r) => setTimeout(r, 300));
    }
  } catch (err) { say("refine: " + err.message); return; }
  if (run === refineRun && !state.refined) status.textContent = "";   // moved on before an answer
}

async function showRefined(job, x, basis, current) {
  const img = new Image();
  img.src = `/api/reference/${job.id}/refined.png?exposure=${state.exposure}`;
  try { await img.decode(); } catch (e) { return false; }
  if (!current()) return false;
  $("scene").getContext("2d").drawImage(img, 0, 0);
  state.refined = { x, basis, exposure: state.exposure, job: job.id };
  $("scene").dataset.refined = job.id;
  return true;
}

// Whether a frame from the server would replace the refined image of the same point (it keeps it).
function keepsRefined(meta) {
  const r = state.refined;
  if (r && sameX(meta.x, r.x) && meta.basis === r.basis && meta.exposure === r.exposure && sameX(r.x, state.x)
      && state.basis === r.basis) return true;
  if (r) { state.refined = null; delete $("scene").dataset.refined; $("refine-status").textContent = ""; }
  return false;
}
