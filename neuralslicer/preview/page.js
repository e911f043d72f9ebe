// preview.html's controls: decode the embedded moves, draw them with plotly.js, redraw on every control.
(function () {
  "use strict";
  var TRAVEL = 0, PRINT = 1;
  var D = JSON.parse(document.getElementById("preview-data").textContent);
  var TYPES = {uint8: Uint8Array, uint16: Uint16Array, uint32: Uint32Array, int16: Int16Array};
  var $ = function (id) { return document.getElementById(id); };
  var state = window.neuralslicerPreview = {ready: false, drawMs: null, draws: 0, level: 0, drawn: {},
    marks: {start: performance.now()}};

  function decode(a) {
    var bin = atob(a.b64), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new TYPES[a.dtype](bytes.buffer);
  }

  function values(a) {
    var q = decode(a), out = new Float32Array(q.length);
    for (var i = 0; i < q.length; i++) out[i] = a.offset + a.scale * q[i];
    return out;
  }

  var n = D.n, X = values(D.x), Y = values(D.y), Z = values(D.z);
  var AX = decode(D.axis), LAYER = decode(D.layer), KIND = decode(D.kind), MOVE = decode(D.move);
  var LEVEL = decode(D.level), nLevels = 1;
  for (var l = 0; l < n; l++) if (LEVEL[l] + 1 > nLevels) nLevels = LEVEL[l] + 1;
  var COLOUR = {layer: LAYER, tilt: values(D.tilt), feed: values(D.feed), width: values(D.width)};
  var HITS = decode(D.collisions);
  var layerMin = D.ranges.layer[0], layerMax = D.ranges.layer[1];

  function ordinal(k) { return k + (k % 10 === 2 && k % 100 !== 12 ? "nd" : k % 10 === 3 && k % 100 !== 13 ? "rd" : "th"); }

  function fmt(v, digits) { return Number(v).toLocaleString("en", {maximumFractionDigits: digits}); }

  function setupControls() {
    $("title").textContent = D.title;
    var s = D.stats, parts = [];
    if (s.n_layers !== undefined) parts.push(fmt(s.n_layers, 0) + " layers");
    if (s.estimated_print_time_s !== undefined) parts.push("print time " + fmt(s.estimated_print_time_s / 3600, 2) + " h");
    if (s.toolpath_length_mm !== undefined) parts.push("toolpath " + fmt(s.toolpath_length_mm / 1000, 1) + " m");
    var hitAll = D.decimation.n_collided;
    parts.push(fmt(hitAll, 0) + " colliding moves (red" + (hitAll > HITS.length ? ", " + fmt(HITS.length, 0) +
      " of them marked" : "") + ")");
    $("figures").textContent = parts.join(" · ");
    var dec = D.decimation;
    $("decimation").textContent = "Kept in this page: " + fmt(dec.n_drawn, 0) + " of " + fmt(dec.n_drawable, 0) +
      " moves that move the tool tip (" + fmt(dec.n_moves, 0) + " in the program), 1 in " + fmt(dec.factor, 1) +
      (dec.factor > 1 ? "; the moves left out lie within " + fmt(dec.max_deviation_mm, 3) +
        " mm of the lines drawn (mean " + fmt(dec.mean_deviation_mm, 4) + " mm)" : "") +
      ". A view of more than " + fmt(D.draw_budget, 0) + " moves draws a coarser level. Tool tip and axis: the " +
      "machine profile's forward kinematics of the program's machine coordinates, in the part frame.";
    ["layer-lo", "layer-hi"].forEach(function (id, k) {
      var el = $(id);
      el.min = layerMin; el.max = layerMax; el.step = 1; el.value = k ? layerMax : layerMin;
    });
    D.modes.forEach(function (m) {
      var o = document.createElement("option");
      o.value = m.key; o.textContent = m.label + (m.unit ? " (" + m.unit + ")" : "");
      $("colour").appendChild(o);
    });
    $("move").min = 0; $("move").max = Math.max(n - 1, 0); $("move").step = 1;
    var lastPrint = n - 1;
    while (lastPrint > 0 && KIND[lastPrint] !== PRINT) lastPrint--;
    $("move").value = HITS.length ? HITS[0] : Math.max(lastPrint, 0);
  }

  function layerRange() {
    var lo = +$("layer-lo").value, hi = +$("layer-hi").value;
    return lo <= hi ? [lo, hi] : [hi, lo];
  }

  function shown(i, r) { return LAYER[i] >= r[0] && LAYER[i] <= r[1]; }

  // the finest detail level whose moves in the layer range fit the draw budget
  function levelFor(r) {
    var count = new Float64Array(nLevels), i, l;
    for (i = 0; i < n; i++) if (shown(i, r)) count[LEVEL[i]]++;
    for (l = nLevels - 2; l >= 0; l--) count[l] += count[l + 1];
    for (l = 0; l < nLevels - 1; l++) if (count[l] <= D.draw_budget) return l;
    return nLevels - 1;
  }

  // lines through the moves of one kind at a detail level in the layer range: each move from the pose before it at
  // that level, NaN between runs
  function lines(kind, r, level, colour) {
    var cap = 3 * n + 3, x = new Float32Array(cap), y = new Float32Array(cap), z = new Float32Array(cap);
    var c = colour ? new Float32Array(cap) : null, m = 0, open = false, prev = -1;
    for (var i = 0; i < n; i++) {
      if (LEVEL[i] < level) continue;
      if (prev < 0 || KIND[i] !== kind || !shown(i, r)) { open = false; prev = i; continue; }
      if (!open) {
        if (m) { x[m] = y[m] = z[m] = NaN; if (c) c[m] = c[m - 1]; m++; }
        x[m] = X[prev]; y[m] = Y[prev]; z[m] = Z[prev]; if (c) c[m] = colour[i]; m++;
        open = true;
      }
      x[m] = X[i]; y[m] = Y[i]; z[m] = Z[i]; if (c) c[m] = colour[i]; m++;
      prev = i;
    }
    state.drawn[kind] = m;
    return {x: x.subarray(0, m), y: y.subarray(0, m), z: z.subarray(0, m), c: c ? c.subarray(0, m) : null};
  }

  function modeOf(key) { return D.modes.filter(function (m) { return m.key === key; })[0]; }

  function printTrace(r, level) {
    var key = $("colour").value, mode = modeOf(key), l = lines(PRINT, r, level, COLOUR[key]), range = D.ranges[key];
    return {type: "scatter3d", mode: "lines", name: "print", x: l.x, y: l.y, z: l.z, hoverinfo: "x+y+z",
      line: {width: 3, color: l.c, colorscale: "Viridis", cmin: range[0], cmax: range[1] > range[0] ? range[1] : range[0] + 1,
        showscale: true, colorbar: {title: {text: mode.label + (mode.unit ? " (" + mode.unit + ")" : "")}, thickness: 14}}};
  }

  function travelTrace(r, level) {
    var l = $("travels").checked ? lines(TRAVEL, r, level, null) : {x: [], y: [], z: []};
    return {type: "scatter3d", mode: "lines", name: "travel", x: l.x, y: l.y, z: l.z, hoverinfo: "skip",
      line: {width: 1, color: "rgba(120,120,120,0.6)"}, visible: $("travels").checked ? true : "legendonly"};
  }

  function collisionTrace(r) {
    var x = [], y = [], z = [];
    if ($("collisions").checked) {
      for (var k = 0; k < HITS.length; k++) {
        var i = HITS[k];
        if (shown(i, r)) { x.push(X[i]); y.push(Y[i]); z.push(Z[i]); }
      }
    }
    return {type: "scatter3d", mode: "markers", name: "collision", x: x, y: y, z: z,
      marker: {size: 4, color: "#e31a1c", symbol: "diamond"}, visible: $("collisions").checked ? true : "legendonly"};
  }

  // cone (apex at the tip, along the tool axis) and holder cylinder, as one triangle mesh
  function headMesh(i) {
    var h = D.head, s = D.axis.scale, a = [AX[3 * i] * s, AX[3 * i + 1] * s, AX[3 * i + 2] * s];
    var norm = Math.hypot(a[0], a[1], a[2]) || 1;
    a = [a[0] / norm, a[1] / norm, a[2] / norm];
    var t = Math.abs(a[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
    var u = [a[1] * t[2] - a[2] * t[1], a[2] * t[0] - a[0] * t[2], a[0] * t[1] - a[1] * t[0]];
    var un = Math.hypot(u[0], u[1], u[2]); u = [u[0] / un, u[1] / un, u[2] / un];
    var v = [a[1] * u[2] - a[2] * u[1], a[2] * u[0] - a[0] * u[2], a[0] * u[1] - a[1] * u[0]];
    var x = [], y = [], z = [], I = [], J = [], K = [], seg = 32, tip = [X[i], Y[i], Z[i]];
    function put(height, radius, ang) {
      var cs = Math.cos(ang) * radius, sn = Math.sin(ang) * radius;
      x.push(tip[0] + a[0] * height + u[0] * cs + v[0] * sn);
      y.push(tip[1] + a[1] * height + u[1] * cs + v[1] * sn);
      z.push(tip[2] + a[2] * height + u[2] * cs + v[2] * sn);
    }
    var L = h.cone_length, rc = L * Math.tan(h.cone_half_angle_deg * Math.PI / 180), R = h.holder_radius;
    var top = L + h.holder_length, k;
    put(0, 0, 0); put(L, 0, 0); put(top, 0, 0);            // 0 apex, 1 holder bottom centre, 2 holder top centre
    for (k = 0; k < seg; k++) {
      var ang = 2 * Math.PI * k / seg;
      put(L, rc, ang); put(L, R, ang); put(top, R, ang);   // 3 + 3k: cone rim, holder bottom rim, holder top rim
    }
    function tri(a, b, c) { I.push(a); J.push(b); K.push(c); }
    for (k = 0; k < seg; k++) {
      var p = 3 + 3 * k, q = 3 + 3 * ((k + 1) % seg);
      tri(0, p, q);                                          // cone side
      tri(p + 1, q + 1, q + 2); tri(p + 1, q + 2, p + 2);    // holder side
      tri(1, p + 1, q + 1); tri(2, p + 2, q + 2);            // holder bottom and top
    }
    return {x: x, y: y, z: z, i: I, j: J, k: K};
  }

  function headTrace() {
    var i = +$("move").value, on = $("head").checked && n > 0, m = on ? headMesh(i) : {x: [], y: [], z: [], i: [], j: [], k: []};
    return {type: "mesh3d", name: "head", x: m.x, y: m.y, z: m.z, i: m.i, j: m.j, k: m.k, color: "#8c8c8c",
      opacity: 0.35, flatshading: true, hoverinfo: "skip", showlegend: true, visible: on ? true : "legendonly"};
  }

  function moveInfo() {
    var i = +$("move").value;
    if (!n) { $("move-info").textContent = "no moves"; return; }
    $("move-number").value = MOVE[i];
    var kind = KIND[i] === PRINT ? "print" : KIND[i] === TRAVEL ? "travel" : "move";
    $("move-info").textContent = "#" + fmt(MOVE[i], 0) + ": layer " + LAYER[i] + ", " + kind + ", tilt " +
      fmt(COLOUR.tilt[i], 1) + "°, feed " + fmt(COLOUR.feed[i], 1) + " mm/s, width " + fmt(COLOUR.width[i], 2) + " mm";
  }

  // the scene: the box of the printing moves (the cone above it), fixed, so that the view holds still as the range
  // changes (travels beyond it, the lifts and the park, are cut off)
  function sceneBox() {
    var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity], P = [X, Y, Z], i, k, any = false;
    for (i = 0; i < n; i++) if (KIND[i] === PRINT) any = true;
    for (i = 0; i < n; i++) {
      if (any && KIND[i] !== PRINT) continue;
      for (k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], P[k][i]); hi[k] = Math.max(hi[k], P[k][i]); }
    }
    if (!n) { lo = [0, 0, 0]; hi = [1, 1, 1]; }
    var size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1e-6), pad = 0.04 * size;
    for (k = 0; k < 3; k++) { lo[k] -= pad; hi[k] += pad; }
    hi[2] += D.head.cone_length;
    var big = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
    return {lo: lo, hi: hi, ratio: {x: (hi[0] - lo[0]) / big, y: (hi[1] - lo[1]) / big, z: (hi[2] - lo[2]) / big}};
  }
  var BOX = sceneBox();

  function layout() {
    var axis = function (t, k) {
      return {title: {text: t + " (mm)"}, range: [BOX.lo[k], BOX.hi[k]], autorange: false, backgroundcolor: "#f7f7f7",
        showbackground: true};
    };
    return {uirevision: "keep", margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: true, legend: {x: 0, y: 1},
      scene: {aspectmode: "manual", aspectratio: BOX.ratio, xaxis: axis("x", 0), yaxis: axis("y", 1),
        zaxis: axis("z", 2), camera: {eye: {x: 1.4, y: -1.4, z: 0.9}}}};
  }

  function traces() {
    var r = layerRange(), level = levelFor(r);
    state.level = level;
    return [printTrace(r, level), travelTrace(r, level), collisionTrace(r), headTrace()];
  }

  function clampMove() {
    var r = layerRange(), first = -1, last = -1;
    for (var i = 0; i < n; i++) if (shown(i, r)) { if (first < 0) first = i; last = i; }
    if (first < 0) return;
    var el = $("move"), v = +el.value;
    el.min = first; el.max = last; el.value = Math.min(Math.max(v, first), last);
  }

  function draw() {
    var r = layerRange();
    clampMove(); moveInfo();
    var tr = traces();
    $("layer-label").textContent = r[0] + "–" + r[1] + " of " + layerMin + "–" + layerMax +
      (state.level ? " (coarser view" + (D.levels[state.level].layer_stride > 1 ? ", every " +
        ordinal(D.levels[state.level].layer_stride) + " layer" : "") + ": narrow the range to see every move)" : "");
    state.marks.traces = state.marks.traces || performance.now();
    return Plotly.react("plot", tr, layout(), {responsive: true, displaylogo: false, plotGlPixelRatio: 1}).then(function () {
      state.marks.plotted = state.marks.plotted || performance.now();
      state.draws += 1;
    });
  }

  var pending = null;
  function redraw() {                      // at most one redraw per 120 ms while a slider is dragged
    if (pending) clearTimeout(pending);
    pending = setTimeout(function () { pending = null; draw(); }, 120);
  }

  function redrawHead() {
    moveInfo();
    var h = headTrace();
    Plotly.restyle("plot", {x: [h.x], y: [h.y], z: [h.z], i: [h.i], j: [h.j], k: [h.k], visible: [h.visible]}, [3]);
  }

  function goToMove(i) {
    var r = layerRange();
    if (!shown(i, r)) { $("layer-lo").value = Math.min(LAYER[i], r[0]); $("layer-hi").value = Math.max(LAYER[i], r[1]); }
    var el = $("move");
    el.min = 0; el.max = Math.max(n - 1, 0); el.value = i;     // (a range input clamps its value to its bounds)
    draw();
  }

  function nearestDrawn(move) {            // the drawn move at or after a program move number (binary search)
    var lo = 0, hi = n - 1;
    while (lo < hi) { var mid = (lo + hi) >> 1; if (MOVE[mid] < move) lo = mid + 1; else hi = mid; }
    return lo;
  }

  function bind() {
    ["layer-lo", "layer-hi"].forEach(function (id) { $(id).addEventListener("input", redraw); });
    ["colour", "travels", "collisions"].forEach(function (id) { $(id).addEventListener("change", draw); });
    $("head").addEventListener("change", redrawHead);
    $("move").addEventListener("input", redrawHead);
    $("move-number").addEventListener("change", function () { goToMove(nearestDrawn(+$("move-number").value)); });
    $("next-collision").disabled = HITS.length === 0;
    $("next-collision").addEventListener("click", function () {
      var cur = +$("move").value, next = HITS[0];
      for (var k = 0; k < HITS.length; k++) if (HITS[k] > cur) { next = HITS[k]; break; }
      goToMove(next);
    });
  }

  state.marks.decoded = performance.now();
  setupControls();
  bind();
  draw().then(function () {
    requestAnimationFrame(function () {
      requestAnimationFrame(function () {
        state.drawMs = performance.now();
        state.ready = true;
      });
    });
  });
})();
