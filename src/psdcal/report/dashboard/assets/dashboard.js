/* psdcal dashboard: the room in 3-D and from above, health, warnings, time controls.
 * Records (see psdcal.report.dashboard.data):
 *   positions [t, emitter, X, Y, Z, sX, sY, sZ, n_sensors, chi2, flag]
 *   tracks    [t, emitter, X, Y, Z, sX, sY, sZ, gated]
 *   sensor    [t, sensor, emitter, snr, chi2, angles or null]
 *   warnings  [t_s or null, t_unix, source, level, text]
 * Read-only: the page sends nothing to the server but its WebSocket handshake. */
(function () {
  'use strict';
  var CFG = JSON.parse(document.getElementById('psd-config').textContent);
  var COLORS = ['#1f77b4', '#ff7f0e', '#2ca02c', '#9467bd', '#8c564b', '#e377c2', '#17becf', '#bcbd22', '#7f7f7f'];
  var MULTI = ['t_s', 'emitter', 'X_mm', 'Y_mm', 'Z_mm', 'sigma_X_mm', 'sigma_Y_mm', 'sigma_Z_mm', 'n_sensors', 'chi2'];
  var TRACK = ['t_s', 'emitter', 'X_mm', 'Y_mm', 'Z_mm', 'sigma_X_mm', 'sigma_Y_mm', 'sigma_Z_mm', 'gated'];
  var HEALTH_S = 1.0;   // the health tables look at the last second of rows
  var S = {room: null, pos: [], trk: [], sen: [], warn: [], tmin: Infinity, tmax: -Infinity,
           follow: true, paused: false, T: null, playing: null, dirty: true, busy: false, bounds: null,
           colors: {}, nColors: 0, arrivals: [], pending: 0, connected: false};
  var drawLog = [];
  var el = function (id) { return document.getElementById(id); };
  var has3d = (function () {
    try { var c = document.createElement('canvas'); return !!(c.getContext('webgl') || c.getContext('experimental-webgl')); }
    catch (e) { return false; }
  })();

  // ---- data ----------------------------------------------------------------------------------------------------
  function insert(arr, r) {
    var i = arr.length;
    while (i > 0 && arr[i - 1][0] > r[0]) i--;
    if (i === arr.length) arr.push(r); else arr.splice(i, 0, r);
    if (r[0] > S.tmax) S.tmax = r[0];
    if (r[0] < S.tmin) S.tmin = r[0];
  }
  function ingest(msg) {
    if (msg.type === 'snapshot') {
      warnKey = null;
      S.pos = []; S.trk = []; S.sen = []; S.warn = []; S.tmin = Infinity; S.tmax = -Infinity;
    }
    if (msg.room) { S.room = msg.room; S.bounds = null; showFiles(); }
    var n = 0;
    [['positions', S.pos], ['tracks', S.trk], ['sensor', S.sen]].forEach(function (p) {
      (msg[p[0]] || []).forEach(function (r) { insert(p[1], r); n++; });
    });
    (msg.warnings || []).forEach(function (w) { S.warn.push(w); });
    trim();
    var now = performance.now();
    S.arrivals.push([now, n]);
    while (S.arrivals.length && S.arrivals[0][0] < now - 1000) S.arrivals.shift();
    if (S.paused) S.pending += n;
    S.dirty = true;
    schedule();
  }
  function trim() {
    var h = S.room && S.room.history_s;
    if (!h || !isFinite(S.tmax)) return;
    var lo = S.tmax - h;
    [S.pos, S.trk, S.sen].forEach(function (a) {
      var k = 0; while (k < a.length && a[k][0] < lo) k++;
      if (k) a.splice(0, k);
    });
    var m = Infinity;
    [S.pos, S.trk, S.sen].forEach(function (a) { if (a.length && a[0][0] < m) m = a[0][0]; });
    S.tmin = m;
  }
  function lastIndex(a, T) {  // last i with a[i][0] <= T, or -1
    var lo = 0, hi = a.length - 1, ans = -1;
    while (lo <= hi) { var mid = (lo + hi) >> 1; if (a[mid][0] <= T) { ans = mid; lo = mid + 1; } else hi = mid - 1; }
    return ans;
  }
  function viewTime() {
    if (S.follow || S.T === null) return S.tmax;
    return S.T;
  }
  function latest(a, T, within) {  // the latest record per emitter with t in (T - within, T]
    var out = {}, i = lastIndex(a, T);
    for (; i >= 0 && a[i][0] > T - within; i--) if (!(a[i][1] in out)) out[a[i][1]] = a[i];
    return out;
  }
  function windowRows(a, T, span) {
    var out = [], i = lastIndex(a, T);
    for (; i >= 0 && a[i][0] > T - span; i--) out.push(a[i]);
    return out.reverse();
  }
  function color(em) {
    if (!(em in S.colors)) S.colors[em] = COLORS[S.nColors++ % COLORS.length];
    return S.colors[em];
  }
  function trailS() { var v = parseFloat(el('trail').value); return isFinite(v) && v >= 0 ? v : 10; }
  function visibleRows() {
    var T = viewTime(), span = Math.max(trailS(), 1e-9);
    return S.pos.length ? {columns: MULTI, rows: windowRows(S.pos, T, span).map(function (r) { return r.slice(0, 10); })}
                        : {columns: TRACK, rows: windowRows(S.trk, T, span)};
  }
  function csvText() {
    var v = visibleRows();
    var cell = function (x) { return x === null || x === undefined ? '' : String(x); };
    return v.columns.join(',') + '\n' + v.rows.map(function (r) { return r.map(cell).join(','); }).join('\n') + (v.rows.length ? '\n' : '');
  }

  // ---- geometry --------------------------------------------------------------------------------------------------
  function ellipse(x, y, a, b) {
    var xs = [], ys = [];
    for (var k = 0; k <= 48; k++) { var th = 2 * Math.PI * k / 48; xs.push(x + a * Math.cos(th)); ys.push(y + b * Math.sin(th)); }
    return [xs, ys];
  }
  function ellipsoid(c, r, acc) {  // adds a UV sphere scaled by r (3) at c (3) to the mesh accumulator
    var nu = 16, nv = 9, base = acc.x.length;
    for (var i = 0; i <= nv; i++) {
      var v = Math.PI * i / nv;
      for (var j = 0; j < nu; j++) {
        var u = 2 * Math.PI * j / nu;
        acc.x.push(c[0] + r[0] * Math.sin(v) * Math.cos(u));
        acc.y.push(c[1] + r[1] * Math.sin(v) * Math.sin(u));
        acc.z.push(c[2] + r[2] * Math.cos(v));
      }
    }
    for (i = 0; i < nv; i++) for (j = 0; j < nu; j++) {
      var p = base + i * nu + j, q = base + i * nu + (j + 1) % nu;
      acc.i.push(p, q); acc.j.push(p + nu, p + nu); acc.k.push(q, q + nu);
    }
  }
  function roomBounds(extra) {
    var pts = [];
    var room = S.room || {};
    (room.sensors || []).forEach(function (s) { pts.push(s.center_mm); });  // not the fields of view: they reach far
    (room.emitters || []).forEach(function (e) { pts.push(e.pos_mm); });
    if (room.plan) { pts.push([room.plan.x_mm[0], room.plan.y_mm[0], 0]); pts.push([room.plan.x_mm[room.plan.x_mm.length - 1], room.plan.y_mm[room.plan.y_mm.length - 1], 0]); }
    extra.forEach(function (p) { pts.push(p); });
    if (!pts.length) return null;
    var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    pts.forEach(function (p) { for (var d = 0; d < 3; d++) { lo[d] = Math.min(lo[d], p[d]); hi[d] = Math.max(hi[d], p[d]); } });
    var pad = 0.12 * Math.max(hi[0] - lo[0], hi[1] - lo[1], 500);
    return [[lo[0] - pad, hi[0] + pad], [lo[1] - pad, hi[1] + pad]];
  }
  function grow(b, pts) {
    if (!b) return roomBounds(pts);
    var out = false;
    pts.forEach(function (p) { if (p[0] < b[0][0] || p[0] > b[0][1] || p[1] < b[1][0] || p[1] > b[1][1]) out = true; });
    return out ? roomBounds(pts) : b;
  }

  var roomCache = {room: null, plan: null, top: null, d3: null};
  function roomTraces(room) {  // the traces that change only with the room: kept, so that Plotly.react skips them
    var planOn = el('planlayer').checked;
    if (roomCache.room === room && roomCache.plan === planOn) return roomCache;
    var top = [], d3 = [];
    // planner map
    if (room.plan && el('planlayer').checked) {
      top.push({type: 'heatmap', x: room.plan.x_mm, y: room.plan.y_mm, z: room.plan.sigma_mm, colorscale: 'Viridis',
                opacity: 0.55, name: 'position 1-sigma (plan)', colorbar: {title: {text: 'sigma mm'}, len: 0.5}, hoverinfo: 'z', uid: 'plan'});
    }
    // sensors and their fields of view
    var fx = [], fy = [], fx3 = [], fy3 = [], fz3 = [];
    room.sensors.forEach(function (s) {
      var c = s.center_mm, f = s.fov_mm;
      f.concat([f[0]]).forEach(function (p) { fx.push(p[0]); fy.push(p[1]); });
      fx.push(null); fy.push(null);
      f.forEach(function (p) { fx3.push(c[0], p[0], null); fy3.push(c[1], p[1], null); fz3.push(c[2], p[2], null); });
      f.concat([f[0]]).forEach(function (p) { fx3.push(p[0]); fy3.push(p[1]); fz3.push(p[2]); });
      fx3.push(null); fy3.push(null); fz3.push(null);
    });
    var sx = room.sensors.map(function (s) { return s.center_mm[0]; });
    var sy = room.sensors.map(function (s) { return s.center_mm[1]; });
    var sz = room.sensors.map(function (s) { return s.center_mm[2]; });
    var sn = room.sensors.map(function (s) { return s.name; });
    top.push({type: 'scatter', mode: 'lines', x: fx, y: fy, name: 'field of view (floor)', line: {color: '#999', width: 1, dash: 'dot'}, hoverinfo: 'skip', uid: 'fov'});
    top.push({type: 'scatter', mode: 'markers+text', x: sx, y: sy, text: sn, textposition: 'top center', name: 'sensors',
              marker: {symbol: 'square', size: 11, color: '#333'}, uid: 'sensors'});
    d3.push({type: 'scatter3d', mode: 'lines', x: fx3, y: fy3, z: fz3, name: 'field of view', line: {color: '#999', width: 2}, hoverinfo: 'skip'});
    d3.push({type: 'scatter3d', mode: 'markers+text', x: sx, y: sy, z: sz, text: sn, name: 'sensors', marker: {symbol: 'square', size: 5, color: '#333'}});
    // surveyed emitters
    var ex = room.emitters.map(function (e) { return e.pos_mm[0]; }), ey = room.emitters.map(function (e) { return e.pos_mm[1]; });
    var ez = room.emitters.map(function (e) { return e.pos_mm[2]; }), en = room.emitters.map(function (e) { return e.name + ' (surveyed)'; });
    top.push({type: 'scatter', mode: 'markers', x: ex, y: ey, text: en, name: 'surveyed emitters', marker: {symbol: 'diamond-open', size: 11, color: '#555'}, uid: 'surveyed'});
    d3.push({type: 'scatter3d', mode: 'markers', x: ex, y: ey, z: ez, text: en, name: 'surveyed emitters', marker: {symbol: 'diamond-open', size: 4, color: '#555'}});
    roomCache = {room: room, plan: planOn, top: top, d3: d3};
    return roomCache;
  }
  // ---- drawing ---------------------------------------------------------------------------------------------------
  function schedule() { if (!S.busy) requestAnimationFrame(draw); }
  function draw() {
    if (!S.dirty || S.busy) { status(); return; }
    S.dirty = false;
    if (S.paused && !S.force) { status(); return; }
    S.force = false;
    S.busy = true;
    var T = viewTime(), trail = trailS();
    var room = S.room || {sensors: [], emitters: []};
    var src = S.pos.length ? S.pos : S.trk;
    var stale = Math.max(trail, 5.0);
    var now = latest(src, T, stale);
    var names = Object.keys(now).sort();
    names.forEach(color);
    S.bounds = grow(S.bounds, names.map(function (n) { return [now[n][2], now[n][3], now[n][4]]; }));
    var trailsSrc = S.trk.length ? S.trk : S.pos;
    var trails = {};
    windowRows(trailsSrc, T, trail).forEach(function (r) { (trails[r[1]] = trails[r[1]] || []).push(r); });
    var rc = roomTraces(room);
    var top = rc.top.slice(), d3 = rc.d3.slice();
    // trails
    Object.keys(trails).sort().forEach(function (em) {
      var rs = trails[em];
      var xs = rs.map(function (r) { return r[2]; }), ys = rs.map(function (r) { return r[3]; }), zs = rs.map(function (r) { return r[4]; });
      top.push({type: 'scatter', mode: 'lines', x: xs, y: ys, name: em + ' track', line: {color: color(em), width: 1.5}, hoverinfo: 'skip', showlegend: false, uid: 'trail-' + em});
      d3.push({type: 'scatter3d', mode: 'lines', x: xs, y: ys, z: zs, name: em + ' track', line: {color: color(em), width: 3}, hoverinfo: 'skip', showlegend: false});
    });
    // each sensor's measured rays (from its angle rows): sensor -> a little past the located emitter, or to the floor
    var rx = [], ry = [], rx3 = [], ry3 = [], rz3 = [], sens = {}, seenRay = {};
    (room.sensors || []).forEach(function (s) { sens[s.name] = s; });
    for (var i = lastIndex(S.sen, T); i >= 0 && S.sen[i][0] > T - 0.5; i--) {
      var q = S.sen[i], key = q[1] + '|' + q[2];
      if (!q[5] || key in seenRay || !sens[q[1]]) continue;
      seenRay[key] = 1;
      var sp = sens[q[1]], Rm = sp.R, c = sp.center_mm;
      var dc = [Math.tan(q[5][0] * Math.PI / 180), Math.tan(q[5][1] * Math.PI / 180), 1], dw = [0, 0, 0];
      for (var j = 0; j < 3; j++) dw[j] = Rm[0][j] * dc[0] + Rm[1][j] * dc[1] + Rm[2][j] * dc[2];
      var nrm = Math.hypot(dw[0], dw[1], dw[2]);
      dw = dw.map(function (v) { return v / nrm; });
      var L = now[q[2]] ? 1.1 * Math.hypot(now[q[2]][2] - c[0], now[q[2]][3] - c[1], now[q[2]][4] - c[2])
                        : (dw[2] < -1e-9 && c[2] > 0 ? -c[2] / dw[2] : 3000);
      rx.push(c[0], c[0] + L * dw[0], null); ry.push(c[1], c[1] + L * dw[1], null);
      rx3.push(c[0], c[0] + L * dw[0], null); ry3.push(c[1], c[1] + L * dw[1], null); rz3.push(c[2], c[2] + L * dw[2], null);
    }
    if (rx.length) {
      top.push({type: 'scatter', mode: 'lines', x: rx, y: ry, name: 'sensor rays', line: {color: 'rgba(31,59,87,0.35)', width: 1}, hoverinfo: 'skip', uid: 'rays'});
      d3.push({type: 'scatter3d', mode: 'lines', x: rx3, y: ry3, z: rz3, name: 'sensor rays', line: {color: 'rgba(31,59,87,0.5)', width: 2}, hoverinfo: 'skip'});
    }
    // 3-sigma ellipses / ellipsoids (the rows carry per-axis sigmas: axes along the room's)
    var elx = [], ely = [], mesh = {x: [], y: [], z: [], i: [], j: [], k: []};
    names.forEach(function (n) {
      var r = now[n], e = ellipse(r[2], r[3], 3 * r[5], 3 * r[6]);
      elx = elx.concat(e[0], [null]); ely = ely.concat(e[1], [null]);
      ellipsoid([r[2], r[3], r[4]], [3 * r[5], 3 * r[6], 3 * r[7]], mesh);
    });
    top.push({type: 'scatter', mode: 'lines', x: elx, y: ely, name: '3-sigma', line: {color: '#d62728', width: 1}, hoverinfo: 'skip', uid: 'ellipses'});
    if (mesh.x.length) d3.push({type: 'mesh3d', x: mesh.x, y: mesh.y, z: mesh.z, i: mesh.i, j: mesh.j, k: mesh.k, opacity: 0.25, color: '#d62728', name: '3-sigma', hoverinfo: 'skip'});
    // located emitters (uid 'located'; a row whose chi2 fails has a red ring)
    var lx = names.map(function (n) { return now[n][2]; }), ly = names.map(function (n) { return now[n][3]; });
    var lz = names.map(function (n) { return now[n][4]; });
    var lc = names.map(color), ring = names.map(function (n) { return now[n].length > 10 && now[n][10] ? '#d00' : '#fff'; });
    var hover = names.map(function (n) {
      var r = now[n];
      return n + '<br>X ' + r[2].toFixed(1) + ' Y ' + r[3].toFixed(1) + ' Z ' + r[4].toFixed(1) + ' mm<br>3-sigma ' +
        (3 * r[5]).toFixed(1) + ' / ' + (3 * r[6]).toFixed(1) + ' / ' + (3 * r[7]).toFixed(1) + ' mm';
    });
    top.push({type: 'scatter', mode: 'markers+text', x: lx, y: ly, text: names, textposition: 'bottom center', hovertext: hover, hoverinfo: 'text',
              name: 'located', marker: {size: 10, color: lc, line: {color: ring, width: 2}}, uid: 'located'});
    d3.push({type: 'scatter3d', mode: 'markers+text', x: lx, y: ly, z: lz, text: names, hovertext: hover, hoverinfo: 'text',
             name: 'located', marker: {size: 5, color: lc}});
    var b = S.bounds || [[0, 1], [0, 1]];
    // the 3-D box: the room's floor plan and from the floor (or the lowest point) to above the highest sensor
    var zs = (room.sensors || []).map(function (s) { return s.center_mm[2]; }).concat((room.emitters || []).map(function (e) { return e.pos_mm[2]; }), lz);
    var zr = [Math.min(0, Math.min.apply(null, zs.concat([0]))), 1.1 * Math.max.apply(null, zs.concat([1000]))];
    var layoutTop = {margin: {l: 60, r: 20, t: 10, b: 50}, showlegend: true, legend: {orientation: 'h', y: -0.12},
                     xaxis: {title: {text: 'X mm'}, range: b[0], zeroline: false},
                     yaxis: {title: {text: 'Y mm'}, range: b[1], zeroline: false, scaleanchor: 'x', scaleratio: 1},
                     uirevision: 'top', plot_bgcolor: '#fff'};
    var layout3d = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: false, uirevision: 'room3d',
                    scene: {aspectmode: 'manual', aspectratio: aspect3d(b, zr),
                            xaxis: {title: {text: 'X mm'}, range: b[0]}, yaxis: {title: {text: 'Y mm'}, range: b[1]},
                            zaxis: {title: {text: 'Z mm'}, range: zr}}};
    var cfg = {displaylogo: false, responsive: true};
    var done = Plotly.react(el('top'), top, layoutTop, cfg);
    if (has3d) draw3d(d3, layout3d, cfg);
    tables(T, now, names);
    warnings(T);
    status();
    done.then(function () {
      requestAnimationFrame(function () {
        drawLog.push({t: T, wall: performance.timeOrigin + performance.now()});
        if (drawLog.length > 20000) drawLog.splice(0, 10000);
        document.body.dataset.drawn = String(drawLog.length);
        S.busy = false;
        if (S.dirty) schedule();
      });
    }, function (err) { S.busy = false; console.error('psdcal dashboard: ' + err); });
  }
  // the 3-D view (WebGL, slow without a GPU) is redrawn at most every MIN_3D_MS, never holding up the view from above
  var MIN_3D_MS = 250, d3state = {busy: false, last: 0, next: null, timer: null};
  function draw3d(traces, layout, cfg) {
    d3state.next = [traces, layout, cfg];
    if (d3state.busy || d3state.timer) return;
    var wait = d3state.last + MIN_3D_MS - performance.now();
    if (wait > 0) { d3state.timer = setTimeout(function () { d3state.timer = null; draw3d.apply(null, d3state.next); }, wait); return; }
    var a = d3state.next; d3state.next = null; d3state.busy = true;
    Plotly.react(el('room3d'), a[0], a[1], a[2]).then(function () {
      d3state.busy = false; d3state.last = performance.now();
      if (d3state.next) draw3d.apply(null, d3state.next);
    }, function (err) { d3state.busy = false; console.error('psdcal dashboard (3-D): ' + err); });
  }
  function aspect3d(b, zr) {  // equal scales on the three axes
    var dx = b[0][1] - b[0][0], dy = b[1][1] - b[1][0], dz = zr[1] - zr[0], m = Math.max(dx, dy, dz);
    return {x: dx / m, y: dy / m, z: dz / m};
  }
  function fmt(x, d) { return x === null || x === undefined ? '' : Number(x).toFixed(d); }
  function tables(T, now, names) {
    var tb = el('emitters').tBodies[0], html = [];
    var recent = S.pos.length ? windowRows(S.pos, T, HEALTH_S) : [];
    names.forEach(function (n) {
      var r = now[n], flagged = recent.filter(function (x) { return x[1] === n && x[10]; }).length;
      var isPos = r.length > 10;
      html.push('<tr class="' + (isPos && r[10] ? 'bad' : flagged ? 'warn' : '') + '" data-emitter="' + esc(n) + '"><td>' + esc(n) + '</td><td>' + fmt(r[2], 1) +
        '</td><td>' + fmt(r[3], 1) + '</td><td>' + fmt(r[4], 1) + '</td><td>' + fmt(3 * r[5], 1) + ' / ' + fmt(3 * r[6], 1) + ' / ' + fmt(3 * r[7], 1) +
        '</td><td>' + (isPos ? fmt(r[8], 0) : '') + '</td><td>' + (isPos ? fmt(r[9], 2) : '') + '</td><td>' + flagged + '</td><td>' + fmt(T - r[0], 2) + '</td></tr>');
    });
    tb.innerHTML = html.join('');
    var lim = -2 * Math.log((S.room && S.room.alpha) || 1e-3);  // chi2(2) quantile 1 - alpha
    var rows = windowRows(S.sen, T, HEALTH_S), per = {};
    rows.forEach(function (r) {
      var p = per[r[1]] = per[r[1]] || {em: {}, snr: [], chi2: []};
      p.em[r[2]] = 1;
      if (r[3] !== null) p.snr.push(r[3]);
      if (r[4] !== null) p.chi2.push(r[4]);
    });
    var sensors = ((S.room && S.room.sensors) || []).map(function (s) { return s.name; });
    Object.keys(per).forEach(function (n) { if (sensors.indexOf(n) < 0) sensors.push(n); });
    html = [];
    sensors.forEach(function (n) {
      var p = per[n] || {em: {}, snr: [], chi2: []};
      var s = ((S.room && S.room.sensors) || []).filter(function (x) { return x.name === n; })[0] || {};
      var snr = p.snr.slice().sort(function (a, b) { return a - b; });
      var med = snr.length ? snr[snr.length >> 1] : null;
      var mean = p.chi2.length ? p.chi2.reduce(function (a, b) { return a + b; }, 0) / p.chi2.length / 2 : null;
      var bad = p.chi2.filter(function (c) { return c > lim; }).length;
      var cls = s.verdict === 'wrong' ? 'bad' : (s.verdict === 'suspect' || bad) ? 'warn' : '';
      html.push('<tr class="' + cls + '" data-sensor="' + esc(n) + '"><td>' + esc(n) + '</td><td>' + esc(s.verdict || (s.calib ? 'no verdict' : '')) +
        '</td><td>' + Object.keys(p.em).sort().map(esc).join(' ') + '</td><td>' + fmt(med, 0) + '</td><td>' + fmt(mean, 2) +
        '</td><td>' + bad + ' of ' + p.chi2.length + '</td></tr>');
    });
    el('sensors').tBodies[0].innerHTML = html.join('');
  }
  function esc(s) { return String(s).replace(/[&<>"']/g, function (c) { return '&#' + c.charCodeAt(0) + ';'; }); }
  var warnKey = null;
  function warnings(T) {
    var shown = S.warn.filter(function (w) { return w[0] === null || w[0] <= T; });
    var key = S.warn.length + '/' + shown.length;
    if (key === warnKey) return;  // unchanged: the list is not rebuilt on every frame
    warnKey = key;
    shown = shown.slice(-300).reverse();
    el('warnings').innerHTML = shown.map(function (w) {
      var when = w[0] !== null ? 't = ' + w[0].toFixed(3) + ' s' : (w[1] ? new Date(w[1] * 1000).toLocaleTimeString() : '');
      return '<li class="' + esc(w[3]) + '"><span class="when">' + esc(when) + '</span><span class="src">' + esc(w[2]) + ':</span> ' + esc(w[4]) + '</li>';
    }).join('');
  }
  function status() {
    var st = el('status'), T = viewTime();
    var mode = CFG.mode === 'static' ? 'static export' : !S.connected ? 'disconnected' : (S.room && S.room.mode === 'replay') ? 'replay x' + S.room.speed : 'live';
    var txt = S.paused ? 'paused (' + S.pending + ' new rows) - ' + mode : S.playing ? 'playing - ' + mode : mode;
    st.textContent = txt;
    st.className = 'status ' + (S.paused ? 'paused' : (CFG.mode === 'live' && !S.connected) ? 'lost' : 'live');
    el('clock').textContent = isFinite(T) ? 't = ' + T.toFixed(3) + ' s' : 't = -';
    var n = S.arrivals.reduce(function (a, b) { return a + b[1]; }, 0);
    el('rate').textContent = CFG.mode === 'live' ? n + ' rows/s' : '';
    el('pause').textContent = S.paused ? 'Resume' : 'Pause';
    if (!S.dragging && isFinite(S.tmax) && S.tmax > S.tmin) el('scrub').value = String((T - S.tmin) / (S.tmax - S.tmin));
    document.body.dataset.viewT = isFinite(T) ? String(T) : '';
  }
  function showFiles() {
    el('files').textContent = S.room && S.room.files ? 'rows: ' + S.room.files.join(', ') : '';
    if (!has3d) el('room3d').textContent = 'This browser has no WebGL: the 3-D view is off (the view from above works).';
  }

  // ---- controls --------------------------------------------------------------------------------------------------
  function redraw() { S.dirty = true; S.force = true; schedule(); }
  function pause() { S.T = viewTime(); S.follow = false; S.paused = true; S.pending = 0; S.playing = null; redraw(); }
  function resume() { S.paused = false; S.follow = true; S.playing = null; S.pending = 0; redraw(); }
  el('pause').addEventListener('click', function () { if (S.paused) resume(); else pause(); });
  el('live').addEventListener('click', resume);
  el('scrub').addEventListener('input', function () {
    S.dragging = true;
    if (!S.paused) pause();
    S.T = S.tmin + parseFloat(el('scrub').value) * (S.tmax - S.tmin);
    redraw();
  });
  el('scrub').addEventListener('change', function () { S.dragging = false; });
  el('trail').addEventListener('change', redraw);
  el('planlayer').addEventListener('change', redraw);
  el('play').addEventListener('click', function () {
    if (!isFinite(S.tmin)) return;
    S.paused = false; S.follow = false; S.T = S.tmin;
    var t0 = performance.now(), from = S.tmin, speed = (S.room && S.room.speed) || 1;
    S.playing = function () {
      if (!S.playing) return;
      S.T = from + (performance.now() - t0) / 1000 * speed;
      if (S.T >= S.tmax) { S.playing = null; S.follow = true; }
      redraw();
      if (S.playing) setTimeout(S.playing, 50);
    };
    S.playing();
  });
  el('png').addEventListener('click', function () {
    Plotly.downloadImage(el('top'), {format: 'png', filename: 'psdcal-dashboard-top'});
    if (has3d) Plotly.downloadImage(el('room3d'), {format: 'png', filename: 'psdcal-dashboard-3d'});
  });
  el('csv').addEventListener('click', function () {
    var a = document.createElement('a');
    a.href = URL.createObjectURL(new Blob([csvText()], {type: 'text/csv'}));
    a.download = 'psdcal-dashboard-rows.csv';
    document.body.appendChild(a); a.click(); a.remove();
  });

  // ---- input -----------------------------------------------------------------------------------------------------
  function connect() {
    var token = new URLSearchParams(location.search).get('token');
    var url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws' + (token ? '?token=' + encodeURIComponent(token) : '');
    var ws = new WebSocket(url);
    ws.onopen = function () { S.connected = true; status(); };
    ws.onmessage = function (ev) { ingest(JSON.parse(ev.data)); };
    ws.onclose = function () { S.connected = false; status(); setTimeout(connect, 1000); };
  }
  window.psdDashboard = {state: S, drawLog: drawLog, viewTime: viewTime, visibleRows: visibleRows, csv: csvText,
                         pause: pause, resume: resume};
  if (CFG.mode === 'static') {
    el('play').hidden = false;
    ingest(JSON.parse(document.getElementById('psd-data').textContent));
  } else {
    el('play').hidden = true;
    connect();
  }
})();
