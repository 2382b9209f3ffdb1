// The BRDF slice at a chosen phi_d and the polar plot of the lobe at a chosen incidence, both
// drawn in the page from the preview table the sphere uses (preview.js: MaterialPreview.table,
// float16 (3, n_h, n_d, n_p), every stride-th bin of the full table).
"use strict";

// One colour scale for every point and every phi_d: log10 of the mean RGB value (1/sr).
const SLICE_RANGE = [-3, 3];
const MAGMA = [[0, 0, 4], [59, 15, 112], [140, 41, 129], [222, 73, 104], [254, 159, 109], [252, 253, 191]];

function magma(t) {
  const u = Math.min(1, Math.max(0, t)) * (MAGMA.length - 1), i = Math.min(MAGMA.length - 2, Math.floor(u)), f = u - i;
  return MAGMA[i].map((v, k) => Math.round(v + f * (MAGMA[i + 1][k] - v)));
}

// theta_h x theta_d at phi_d (degrees, 0..180): theta_d to the right, theta_h (sqrt bins) up.
function drawSlice(preview, canvas, phiDeg) {
  if (!preview || !preview.table) return false;
  const [nh, nd, np] = preview.table.layout.dims;
  const ip = Math.min(np - 1, Math.round(phiDeg / 180 * np - 0.5));
  if (canvas.width !== nd || canvas.height !== nh) { canvas.width = nd; canvas.height = nh; }
  const ctx = canvas.getContext("2d"), img = ctx.createImageData(nd, nh);
  const [lo, hi] = SLICE_RANGE;
  for (let ih = 0; ih < nh; ih++) {
    for (let id = 0; id < nd; id++) {
      const v = preview.value(ih, id, ip), m = (v[0] + v[1] + v[2]) / 3;
      const c = magma((Math.log10(Math.max(m, 10 ** lo)) - lo) / (hi - lo)), o = 4 * ((nh - 1 - ih) * nd + id);
      img.data[o] = c[0]; img.data[o + 1] = c[1]; img.data[o + 2] = c[2]; img.data[o + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  return true;
}

// Rusinkiewicz angles of (wi, wo), as merlAngles in preview.js.
function merlAnglesJs(wi, wo) {
  const h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]], rh = Math.hypot(h[0], h[1]);
  const thetaH = Math.atan2(rh, h[2]), inv = 1 / Math.hypot(rh, h[2]);
  const cph = rh > 0 ? h[0] / rh : 1, sph = rh > 0 ? h[1] / rh : 0, cth = h[2] * inv, sth = rh * inv;
  const dx = (wi[0] * cph + wi[1] * sph) * cth - wi[2] * sth, dy = wi[1] * cph - wi[0] * sph;
  const dz = (wi[0] * cph + wi[1] * sph) * sth + wi[2] * cth;
  let phiD = Math.atan2(dy, dx);
  if (phiD < 0) phiD += Math.PI;
  if (phiD >= Math.PI) phiD -= Math.PI;
  return [thetaH, Math.atan2(Math.hypot(dx, dy), dz), phiD];
}

// The table's value at (wi, wo): the shader's bin mapping, trilinear between texels.
function tableAt(preview, wi, wo) {
  const { dims, full_dims: full, strides } = preview.table.layout, a = merlAnglesJs(wi, wo);
  const c = [Math.sqrt(Math.min(1, Math.max(0, a[0] / (Math.PI / 2)))) * full[0], a[1] / (Math.PI / 2) * full[1],
             a[2] / Math.PI * full[2]];
  const r = c.map((v, k) => Math.min(dims[k] - 0.5, Math.max(0.5, (v - 0.5) / strides[k] + 0.5)) - 0.5);
  const lo = r.map((v, k) => Math.min(Math.floor(v), dims[k] - 1)), f = r.map((v, k) => v - lo[k]);
  const out = [0, 0, 0];
  for (let corner = 0; corner < 8; corner++) {
    const idx = lo.map((v, k) => (corner >> k & 1 ? Math.min(v + 1, dims[k] - 1) : v));
    const w = f.reduce((s, fk, k) => s * (corner >> k & 1 ? fk : 1 - fk), 1);
    if (w === 0) continue;
    const v = preview.value(idx[0], idx[1], idx[2]);
    for (let ch = 0; ch < 3; ch++) out[ch] += w * Math.max(0, v[ch]);
  }
  return out;
}

// Polar plot of f cos(theta_o) in the plane of incidence, light at theta_i (degrees) on the left;
// radius: log10, the top three decades of the curve. Returns the peak direction (degrees).
function drawLobe(preview, canvas, thetaDeg) {
  const ctx = canvas.getContext("2d"), W = canvas.width, H = canvas.height, cx = W / 2, cy = H - 14, R = Math.min(W / 2 - 8, H - 22);
  ctx.fillStyle = "#101216"; ctx.fillRect(0, 0, W, H);
  ctx.strokeStyle = "#2e333b"; ctx.lineWidth = 1;
  for (const f of [1 / 3, 2 / 3, 1]) { ctx.beginPath(); ctx.arc(cx, cy, R * f, Math.PI, 2 * Math.PI); ctx.stroke(); }
  for (let a = -90; a <= 90; a += 30) {
    const t = a * Math.PI / 180;
    ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(cx + R * Math.sin(t), cy - R * Math.cos(t)); ctx.stroke();
  }
  if (!preview || !preview.table) return null;
  const ti = thetaDeg * Math.PI / 180, wi = [-Math.sin(ti), 0, Math.cos(ti)], samples = [];
  for (let k = 0; k <= 178; k++) {
    const to = (k - 89) * Math.PI / 180, wo = [Math.sin(to), 0, Math.cos(to)];
    samples.push([to, tableAt(preview, wi, wo).map((v) => v * Math.cos(to))]);
  }
  const peak = Math.max(1e-12, ...samples.flatMap((s) => s[1])), top = Math.log10(peak), decades = 3;
  const radius = (v) => R * Math.max(0, (Math.log10(Math.max(v, 1e-30)) - top + decades) / decades);
  ["#ff6b6b", "#7ee787", "#79c0ff"].forEach((colour, ch) => {
    ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
    samples.forEach(([to, v], k) => {
      const r = radius(v[ch]), x = cx + r * Math.sin(to), y = cy - r * Math.cos(to);
      if (k) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    ctx.stroke();
  });
  ctx.strokeStyle = "#f0b54a"; ctx.lineWidth = 2; ctx.beginPath();   // the incident light
  ctx.moveTo(cx - R * Math.sin(ti), cy - R * Math.cos(ti)); ctx.lineTo(cx, cy); ctx.stroke();
  ctx.fillStyle = "#8b939e"; ctx.font = "10px system-ui";
  ctx.fillText("light", cx - R * Math.sin(ti) - 10, Math.max(10, cy - R * Math.cos(ti) - 4));
  ctx.fillText(`peak ${peak.toExponential(1)}`, W - 70, 12);
  let best = 0;
  samples.forEach((s, k) => { if (s[1][1] > samples[best][1][1]) best = k; });
  return best - 89;
}
