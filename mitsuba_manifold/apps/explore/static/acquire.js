// The page's acquisition: a photo of the basis's scene (and an optional mask) is sent to
// POST /api/acquire, its progress polled, and the answer shown: the material in words (on the map
// when a latent point explains the photo as well, else a named combination, "beyond the manifold"
// where its weights leave the simplex), the contact sheet (photo | acquired | best single), the
// warnings and the weights. state.acquired: null, or { id, state, progress, stage, result }.
"use strict";

function readFile(file) {   // a file as a data: URL (the JSON body carries it as base64)
  return new Promise((resolve, reject) => {
    const r = new FileReader();
    r.onload = () => resolve(r.result);
    r.onerror = () => reject(new Error(`cannot read ${file.name}`));
    r.readAsDataURL(file);
  });
}

async function startAcquire() {
  const photo = $("acq-photo").files[0], mask = $("acq-mask").files[0], limit = state.info.max_upload;
  if (!photo) return;
  const size = 4 / 3 * (photo.size + (mask ? mask.size : 0));
  if (limit && size > limit) {
    setStatus(`acquire: the files are ${(size / 2 ** 20).toFixed(1)} MiB as sent, the server takes at most ${(limit / 2 ** 20).toFixed(0)} MiB`, true, "acquire");
    return;
  }
  update({ acquired: { state: "starting", progress: 0, stage: "sending the photo" } });
  try {
    const body = { basis: state.basis, photo: await readFile(photo), mask: mask ? await readFile(mask) : null };
    const job = await (await api("/api/acquire", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body) })).json();
    update({ acquired: { id: job.id, state: job.state, progress: 0, stage: job.stage } });
    pollAcquire(job.id);
  } catch (e) { update({ acquired: null }); setStatus("acquire: " + e.message, true, "acquire"); }
}

async function pollAcquire(id) {
  let job;
  try { job = await (await api("/api/acquire/" + id)).json(); }
  catch (e) { update({ acquired: null }); setStatus("acquire: " + e.message, true, "acquire"); return; }
  if (job.state === "queued" || job.state === "running") {
    update({ acquired: { id, state: job.state, progress: job.progress, stage: job.stage } });
    setTimeout(() => pollAcquire(id), 400);
    return;
  }
  if (job.state === "failed") { update({ acquired: null }); setStatus("acquire: " + job.message, true, "acquire"); return; }
  clearError("acquire");
  update({ acquired: { id, state: "done", progress: 1, result: job.result } });
  drawMap();   // its place on the map
}

// The acquired point on the map (app.js's drawMap calls it): a diamond where it is a latent point.
function drawAcquired(ctx) {
  const a = state.acquired, r = a && a.result;
  if (!r || !r.latent.on_map || !state.map) return;
  const [px, py] = toCanvas(r.latent.x);
  ctx.save();
  ctx.translate(px, py); ctx.rotate(Math.PI / 4);
  ctx.lineWidth = 2; ctx.strokeStyle = "#000"; ctx.strokeRect(-7, -7, 14, 14);
  ctx.strokeStyle = "#f0b54a"; ctx.lineWidth = 2; ctx.strokeRect(-5.5, -5.5, 11, 11);
  ctx.restore();
  ctx.fillStyle = "#f0b54a"; ctx.font = "bold 12px system-ui"; ctx.fillText("photo", px + 9, py + 14);
}

function drawAcquire() {   // a view of store.js: the acquisition panel from state.acquired
  const a = state.acquired, running = !!a && a.state !== "done", bar = $("acq-progress");
  const b = state.info.bases.find((b) => b.name === state.basis);
  setText($("acq-basis"), `basis ${b.name} · ${b.resolution.join("×")}`);
  $("acq-start").disabled = running || !$("acq-photo").files.length;
  bar.hidden = !running;
  if (running) {
    bar.firstElementChild.style.width = (100 * a.progress).toFixed(0) + "%";
    setText(bar.lastElementChild, a.stage || "");
  }
  const r = a && a.state === "done" ? a.result : null;
  $("acq-result").hidden = $("acq-weights-col").hidden = !r;
  if (!r || $("acq-result").dataset.job === a.id) return;
  $("acq-result").dataset.job = a.id;
  const beyond = r.beyond.length ? ` <span class="beyond">beyond the manifold (${escapeHtml(r.beyond.join(", "))})</span>` : "";
  $("acq-name").innerHTML = escapeHtml(r.description) + beyond;
  setText($("acq-fit"), `basis ${r.basis} · relative error ${fmtNum(r.error)} · best single ${fmtNum(r.single.error)}`);
  const where = $("acq-where"), lx = r.latent.x.map((v) => fmtNum(v)).join(", ");
  where.innerHTML = "";
  if (r.latent.on_map) {
    const go = document.createElement("button");
    go.textContent = "go to it on the map";
    go.title = "the point whose weights explain the photo as well as the acquired ones";
    go.onclick = () => { setX(r.latent.x); commitPoint(); };
    const t = document.createElement("span"); t.className = "small";
    t.textContent = `on the map at x = (${lx}): that point explains the photo as well (error ${fmtNum(r.latent.error)})`;
    where.append(go, t);
  } else {
    const t = document.createElement("span"); t.className = "small muted";
    t.textContent = `not a point of the map: the latent point closest to the photo (${lx}) ` +
      (r.latent.plausible ? `leaves error ${fmtNum(r.latent.error)}` : "is not a plausible material (albedo outside [0, 1])") +
      "; the material is this combination of measured materials";
    where.append(t);
  }
  $("acq-sheet").src = `/api/acquire/${a.id}/sheet.png`;
  $("acq-save").href = `/api/acquire/${a.id}/sheet.png`;
  $("acq-warnings").innerHTML = r.warnings.concat(r.notes).map((w) => `<div class="warn">${escapeHtml(w)}</div>`).join("");
  const ws = Object.entries(r.weights).filter(([, w]) => Math.abs(w) > 5e-4).sort((p, q) => Math.abs(q[1]) - Math.abs(p[1]));
  const max = Math.max(...ws.map(([, w]) => Math.abs(w)), 1e-9), sum = Object.values(r.weights).reduce((s, w) => s + w, 0);
  $("acq-weights").innerHTML = "";
  for (const [n, w] of ws) {
    const half = 50 * Math.abs(w) / max;
    const name = document.createElement("div"); name.className = "name"; name.textContent = n;
    name.title = "go to this measured material"; name.onclick = () => { goTo(n); commitPoint(); };
    const track = document.createElement("div"); track.className = "track";
    const bar = document.createElement("div"); bar.className = "bar" + (w < 0 ? " neg" : "");
    bar.style.left = (w < 0 ? 50 - half : 50) + "%"; bar.style.width = half + "%";
    track.appendChild(bar);
    const val = document.createElement("div"); val.className = "val"; val.textContent = w.toFixed(3);
    $("acq-weights").append(name, track, val);
  }
  setText($("acq-weights-note"), `${ws.length} of ${state.info.names.length} non-zero · sum ${sum.toFixed(3)}`);
  const sp = r.spread;
  $("acq-details").textContent = [
    `feasible set ${r.feasible} (method ${r.method}) · regularisation ${fmtNum(r.regularisation, 4)} (cross-validated)`,
    `solved on the basis's ${r.model}; shown: its ${r.blend} blend · ${r.pixels} pixels`,
    sp ? `spread of near-equally good answers: albedo ${(100 * sp.albedo_spread).toFixed(0)}%, gloss ${(100 * sp.peak_spread).toFixed(0)}% · ${sp.effective_rank} directions of the weights determined` : "",
    `${r.time_s.toFixed(1)} s`,
  ].filter(Boolean).join("\n");
}
view(["acquired", "basis"], drawAcquire);

async function copyAcquired() {
  const r = state.acquired && state.acquired.result;
  if (r) await copy(r.snippet, "acquired material's XML");
}

function bindAcquire() {
  $("acq-photo").onchange = drawAcquire;
  $("acq-start").onclick = startAcquire;
  $("acq-copy").onclick = copyAcquired;
  drawAcquire();
}
