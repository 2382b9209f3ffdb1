// The page's one state (app.js: `state`) and the parts of the page drawn from it. A change goes
// through update(patch): the patch is applied (with the rules that tie fields together: a point
// chosen ends the search filter and the refine status of another point), then every part that
// reads a changed field is drawn again from the state, at once. The point, the search filter, the
// material and snippet, the favourites and compare lists, the refine status, the reference render
// and the header's status and errors are all kept here. Undo/redo, drags, search, links and path
// scrubbing all change the point this way (app.js: setX), so no part can keep a value of an
// earlier point.
"use strict";

const views = [];   // [{ keys, draw }] in the order registered

// A part of the page: draw() reads the state and sets that part; it runs after every update that
// changes one of `keys`.
function view(keys, draw) { views.push({ keys, draw }); }

// The rules applied to every patch before it is stored.
function withRules(patch) {
  if ("x" in patch && !("filter" in patch)) patch = Object.assign({ filter: "" }, patch);   // a point chosen ends the search filter
  if ("x" in patch && !("refine" in patch) && state.refine && !sameX(state.refine.x, patch.x)) {
    patch = Object.assign({ refine: null }, patch);   // the refine status is that of its point only
  }
  return patch;
}

// Apply `patch` to the state; draw again every part reading a field that changed (fields are
// compared by identity: a new array is a change). Returns the changed fields.
function update(patch) {
  patch = withRules(patch);
  const changed = Object.keys(patch).filter((k) => state[k] !== patch[k]);
  Object.assign(state, patch);
  if (!changed.length) return changed;
  for (const v of views) if (v.keys.some((k) => changed.includes(k))) v.draw();
  return changed;
}
