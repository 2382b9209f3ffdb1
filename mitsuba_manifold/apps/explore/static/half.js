// Half-float bits -> float, for the page (the plots read the preview table) and the sphere's worker
// (preview_worker.js: the environment map arrives as float16).
"use strict";

const HALF_TO_FLOAT = (() => {
  const out = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    out[h] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return out;
})();

