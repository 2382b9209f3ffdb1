// Refinement on release: where a drag ends (or a point is chosen), the server renders
// what the basis cannot give at that point (its L2+ light; blend.py --refine) in passes and checks
// the blend shown against that unbiased estimate. The blend stays on screen: at a few spp the
// refinement is noisier than the blend (fireflies where light runs through a narrow peak), and its
// noise, estimated from a few passes, can be too low where fireflies are rare. The status says
// whether the blend agrees within that noise; "show refined" draws the refined image until the
// point or the basis changes (a new exposure re-exposes it: reexposeRefined). The status is
// state.refine (store.js: null, or the point it is for, its text, the check's detail and the job
// the "show refined" button offers), drawn by drawRefine. Uses app.js's state, $, api, sameX,
// fmtNum and requestFrame.
"use strict";

let refineRun = 0;

function refineAvailable() {
  const box = $("refine-auto");
  return box && box.checked && state.x && state.basis && !state.dragging && $("ref-note").hidden;
}

async function refineHere() {
  if (!refineAvailable()) return;
  const x = state.x.slice(), basis = state.basis, run = ++refineRun;
  const current = () => run === refineRun && sameX(x, state.x) && state.basis === basis && !state.dragging &&
                        $("refine-auto").checked;
  const say = (text, more = {}) => {
    if (current()) update({ refine: Object.assign({ x, basis, text, detail: "", offer: null }, state.refine, { text, offer: null }, more) });
  };
  update({ refine: null });
  say("refining…");
  try {
    let job = await (await api("/api/reference", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ basis, x, spp: +$("refine-spp").value, kind: "refine", tab: TAB }) })).json();
    state.refineJob = job.id;
    while (current()) {
      job = await (await api("/api/reference/" + job.id)).json();
      if (!current()) break;
      if (job.state === "failed") { say("refine failed: " + job.message); return; }
      const e = job.error || {};
      if (state.refined && state.refined.job === job.id) { /* shown: its status stays until a move */ }
      else if (e.agrees == null) say(job.state === "done" ? job.message : `refining… ${job.message}`);   // done: nothing to check
      else {
        say(e.agrees ? `full GI checked (${job.message}): the blend agrees with the unbiased render`
                     : `full GI checked (${job.message}): the blend differs from the unbiased render`, {
          detail: `refinement: the blend's relative MSE against the unbiased ` +
            `render is ${fmtNum(e.blend_rel_mse, 3)}, its own estimated noise ${fmtNum(e.noise_rel_mse, 3)} (agrees: within 2×)`,
          offer: state.refined ? null : { job, show: () => showRefined(job, x, basis, current).then((ok) => {
            if (ok) say(`showing the unbiased render (${job.message}; noisy at few spp); move to go back to the blend`);
          }) } });
      }
      if (job.state === "done") return;
      await new Promise((r) => setTimeout(r, 300));
    }
  } catch (err) { say("refine: " + err.message); return; }
  if (run === refineRun && !state.refined) clearRefined();   // moved on before an answer
}

// Refine turned off: the running refinement is cancelled and its status and image go.
function refineOff() {
  refineRun++;
  if (state.refineJob) api(`/api/reference/${state.refineJob}/cancel`, { method: "POST" }).catch(() => {});
  state.refineJob = null;
  const shown = !!state.refined;
  clearRefined();
  if (shown) requestFrame();   // back to the blend of the point
}

function clearRefined() {   // back to blends: the refined image and the last check are gone
  state.refined = null; delete $("scene").dataset.refined; delete $("scene").dataset.refinedExposure;
  update({ refine: null });
}

function drawRefine() {   // a view of store.js: the refine status, its detail and the "show refined" button
  const r = state.refine;
  setText($("refine-status"), r ? r.text : "");
  setText($("refine-detail"), r ? r.detail : "");
  $("refine-show").hidden = !(r && r.offer);
}
view(["refine"], drawRefine);

async function showRefined(job, x, basis, current) {
  const exposure = state.exposure, img = await refinedImage(job.id, exposure);
  if (!img || !current()) return false;
  $("scene").getContext("2d").drawImage(img, 0, 0);
  state.refined = { x, basis, exposure, job: job.id };
  $("scene").dataset.refined = job.id;
  $("scene").dataset.refinedExposure = exposure;
  if (state.exposure !== exposure) reexposeRefined();   // the exposure moved while the image loaded
  return true;
}

async function refinedImage(id, exposure) {   // the refined image tonemapped at `exposure`, or null
  const img = new Image();
  img.src = `/api/reference/${id}/refined.png?exposure=${exposure}`;
  try { await img.decode(); } catch (e) { return null; }
  return img;
}

// The exposure changed while the refined image is shown: the same image, tonemapped again by the
// server at the new exposure (an answer for an exposure changed since is dropped).
// Returns whether it does (a refined image is shown), at once; the image follows.
let reexposeRun = 0;
function reexposeRefined() {
  const r = state.refined;
  if (!r) return false;
  const exposure = state.exposure, run = ++reexposeRun;
  refinedImage(r.job, exposure).then((img) => {
    if (run !== reexposeRun || state.refined !== r || state.exposure !== exposure) return;
    if (!img) {   // the refinement is gone (trimmed): back to the blend at this exposure
      clearRefined();
      requestFrame();
      return;
    }
    $("scene").getContext("2d").drawImage(img, 0, 0);
    r.exposure = exposure;
    $("scene").dataset.refinedExposure = exposure;
  });
  return true;
}

// Whether a frame from the server would replace the refined image of the same point (it keeps it,
// at any exposure: reexposeRefined tonemaps it again).
function keepsRefined(meta) {
  const r = state.refined;
  if (r && sameX(meta.x, r.x) && meta.basis === r.basis && sameX(r.x, state.x) && state.basis === r.basis) return true;
  if (r || state.dragging) clearRefined();
  return false;
}
