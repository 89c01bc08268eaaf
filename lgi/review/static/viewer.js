// lgi shot review viewer: one shaded mesh with per-vertex colours, markers as points, an orbit camera, per-frame
// curves. Plain WebGL 1 and 2D canvas, written for lgi; it reads the data scripts beside it (review_meta.js,
// review_frames.js) and fetches nothing, so the page works from file:// with no server and no network.
"use strict";
(function () {
  const META = window.LGI_REVIEW_META, DATA = window.LGI_REVIEW_FRAMES;
  const T_SCRIPTS = performance.now();
  // Status colours: what the solve is sure of in greens and blues, what it is unsure of in warm colours.
  const STATUS_RGB = {
    contained: [0.20, 0.80, 0.30], projected: [1.00, 0.60, 0.10], neighbour: [0.30, 0.60, 1.00],
    fitted: [0.65, 0.85, 0.95], missing: [0.95, 0.15, 0.15], bridged: [0.85, 0.30, 0.85],
    ray: [1.00, 0.95, 0.20], other: [0.60, 0.60, 0.60],
  };
  const $ = (id) => document.getElementById(id);
  const api = { ready: false, error: null, timing: {} };
  window.lgiReview = api;

  // ---------------------------------------------------------------- decoding
  function b64bytes(s) {
    if (Uint8Array.fromBase64) return Uint8Array.fromBase64(s);
    const bin = atob(s), out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }
  const TYPES = { u1: Uint8Array, i1: Int8Array, u2: Uint16Array, i2: Int16Array, i4: Int32Array, u4: Uint32Array,
                  f4: Float32Array };
  async function decode(b) {
    let bytes = b64bytes(b.b64);
    if (b.gzip) {
      // The browser's own gzip: a Response over a stream, not a fetch, so file:// does not matter.
      const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
      bytes = new Uint8Array(await new Response(stream).arrayBuffer());
    }
    const T = TYPES[b.dtype];
    return new T(bytes.buffer, bytes.byteOffset, bytes.byteLength / T.BYTES_PER_ELEMENT);
  }

  // The frames are stored as frame-to-frame differences, low bytes then high bytes (they compress better):
  // Int16Array stores wrap as numpy's int16 arithmetic does, so the running sum restores the codes exactly.
  function deltaPlanes(bytes, perFrame) {
    const n = bytes.length / 2, out = new Int16Array(n);
    for (let i = 0; i < n; i++) out[i] = bytes[i] | (bytes[n + i] << 8);
    for (let i = perFrame; i < n; i++) out[i] += out[i - perFrame];
    return out;
  }

  // ---------------------------------------------------------------- small maths
  function normalize(v) { const l = Math.hypot(v[0], v[1], v[2]) || 1; return [v[0] / l, v[1] / l, v[2] / l]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function lookAt(eye, target, up) {
    const z = normalize(sub(eye, target)), x = normalize(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }
  function mul(a, b) {  // column-major 4x4: a * b
    const o = new Array(16);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      let s = 0; for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k]; o[c * 4 + r] = s;
    }
    return o;
  }
  // A perceptual-ish ramp (dark blue, teal, yellow, red) for the colour maps.
  const RAMP = [[0.10, 0.15, 0.45], [0.10, 0.55, 0.70], [0.35, 0.80, 0.45], [0.98, 0.85, 0.20], [0.85, 0.15, 0.10]];
  function ramp(t) {
    t = Math.min(1, Math.max(0, t)) * (RAMP.length - 1);
    const i = Math.min(RAMP.length - 2, Math.floor(t)), f = t - i, a = RAMP[i], b = RAMP[i + 1];
    return [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f];
  }
  // A map's codes 0..top are its ramp; codes above top (a map with gaps: the scan map) say why a vertex has no
  // value, in colours outside the ramp, so that a gap never reads as 0 mm.
  const SHADED = [0.78, 0.74, 0.70];
  const GAP_RGB = { 254: [0.30, 0.30, 0.32], 255: SHADED };
  function lut(top) {
    const out = new Float32Array(256 * 3);
    for (let k = 0; k < 256; k++) out.set(k <= top ? ramp(k / top) : (GAP_RGB[k] || SHADED), 3 * k);
    return out;
  }

  // ---------------------------------------------------------------- state
  const S = { frame: 0, loaded: 1, playing: false, speed: 1, map: "none", showMarkers: true, yaw: 0, pitch: 0, dist: 1,
              target: [0, 0, 0], radius: 1, hover: -1, pinned: -1, acc: 0, last: 0 };
  let nF, nV, nM, tris, rest, moving, codes, scale, maps = {}, mv, mw, status, present, diag = [];
  let pos, nrm, col, mpos, mcol, gl, prog, pprog, buf = {}, curves;

  async function load() {
    const t0 = performance.now();
    nF = DATA.n_frames; nV = META.n_vertices; nM = META.markers.length;
    [tris, rest, moving, mv, mw, status, present] = await Promise.all([
      decode(META.triangles), decode(DATA.rest), decode(DATA.moving),
      decode(META.marker_vertices), decode(META.marker_weights), decode(META.status), decode(META.diag_present)]);
    scale = DATA.scale;
    codes = new Int16Array(nF * moving.length * 3);
    for (const m of DATA.maps) {
      const mm = { ...m, top: m.top || 255 };
      mm.lut = lut(mm.top);
      if (m.slots) {
        // A sparse map (frames with a scan only): slot k of the values is the k-th such frame; a block's codes go
        // at its first slot.
        mm.blockStart = [];
        let n = 0;
        for (let f = 0; f < nF; f++) { if (f % DATA.block === 0) mm.blockStart.push(n); if (m.slots[f] >= 0) n++; }
        mm.values = new Uint8Array(n * nV);
      } else mm.values = new Uint8Array(nF * nV);
      maps[m.key] = mm;
    }
    await loadBlock(0);
    S.loaded = Math.min(nF, DATA.block);
    const diagCodes = await Promise.all(META.diagnostics.map((c) => decode(c.data)));
    META.diagnostics.forEach((c, i) => diag.push({ name: c.name, kind: c.kind, values: c.values, codes: diagCodes[i] }));
    api.timing.scripts_ms = T_SCRIPTS - (window.LGI_T0 || 0);
    api.timing.decode_ms = performance.now() - t0;
    pos = new Float32Array(nV * 3); nrm = new Float32Array(nV * 3); col = new Float32Array(nV * 3);
    mpos = new Float32Array(nM * 3); mcol = new Float32Array(nM * 3);
    // The camera frames the shot's first mesh; the faces look down +z with y up, as the datasets store them.
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let v = 0; v < nV; v++) for (let k = 0; k < 3; k++) {
      const x = rest[3 * v + k]; if (x < lo[k]) lo[k] = x; if (x > hi[k]) hi[k] = x;
    }
    S.target = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    S.radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2 || 1;
    S.dist = S.radius * 2.6;
  }

  // The frames come in blocks, each compressed on its own: the first is shown while the others inflate.
  async function loadBlock(k) {
    const per = moving.length * 3, lo = k * DATA.block;
    const [c, ...mapped] = await Promise.all([decode(DATA.blocks[k]), ...DATA.maps.map((m) => decode(m.blocks[k]))]);
    codes.set(deltaPlanes(c, per), lo * per);
    DATA.maps.forEach((m, i) => {
      const mm = maps[m.key];
      mm.values.set(mapped[i], (mm.slots ? mm.blockStart[k] : lo) * nV);
    });
  }
  async function loadRest() {
    // A few blocks at a time: the browser inflates them side by side.
    for (let k = 1; k < DATA.blocks.length; k += 4) {
      const group = [k, k + 1, k + 2, k + 3].filter((j) => j < DATA.blocks.length);
      await Promise.all(group.map(loadBlock));
      S.loaded = Math.min(nF, (group[group.length - 1] + 1) * DATA.block);
      $("status").textContent = S.loaded < nF ? `${META.title} (frames decoded: ${S.loaded}/${nF})` : META.title;
      drawCurves();
    }
    api.timing.all_frames_ms = performance.now() - (window.LGI_T0 || 0);
    api.allLoaded = true;
    $("loadTime").textContent += `, all frames ${fmt(api.timing.all_frames_ms)} ms`;
  }

  // ---------------------------------------------------------------- per frame
  function framePositions(f) {
    pos.set(rest);
    const n = moving.length, base = f * n * 3;
    for (let i = 0; i < n; i++) {
      const v = 3 * moving[i], c = base + 3 * i;
      pos[v] += codes[c] * scale; pos[v + 1] += codes[c + 1] * scale; pos[v + 2] += codes[c + 2] * scale;
    }
    nrm.fill(0);
    for (let t = 0; t < tris.length; t += 3) {
      const a = 3 * tris[t], b = 3 * tris[t + 1], c = 3 * tris[t + 2];
      const ux = pos[b] - pos[a], uy = pos[b + 1] - pos[a + 1], uz = pos[b + 2] - pos[a + 2];
      const wx = pos[c] - pos[a], wy = pos[c + 1] - pos[a + 1], wz = pos[c + 2] - pos[a + 2];
      const nx = uy * wz - uz * wy, ny = uz * wx - ux * wz, nz = ux * wy - uy * wx;
      nrm[a] += nx; nrm[a + 1] += ny; nrm[a + 2] += nz; nrm[b] += nx; nrm[b + 1] += ny; nrm[b + 2] += nz;
      nrm[c] += nx; nrm[c + 1] += ny; nrm[c + 2] += nz;
    }
    for (let m = 0; m < nM; m++) for (let k = 0; k < 3; k++) {
      let s = 0; for (let j = 0; j < 3; j++) s += mw[3 * m + j] * pos[3 * mv[3 * m + j] + k];
      mpos[3 * m + k] = s;
    }
  }
  // The frame's row of a map's values, or -1 where the map has none (a frame without a scan).
  function slotOf(m, f) { return m ? (m.slots ? m.slots[f] : f) : -1; }
  function frameColours(f) {
    const m = maps[S.map], slot = slotOf(m, f);
    if (slot < 0) { for (let i = 0; i < nV * 3; i += 3) col.set(SHADED, i); }
    else {
      const vals = m.values, base = slot * nV, L = m.lut;
      for (let v = 0; v < nV; v++) { const k = 3 * vals[base + v]; col[3 * v] = L[k]; col[3 * v + 1] = L[k + 1]; col[3 * v + 2] = L[k + 2]; }
    }
    for (let i = 0; i < nM; i++) {
      const c = STATUS_RGB[META.statuses[status[f * nM + i]]] || STATUS_RGB.other; mcol.set(c, 3 * i);
    }
  }

  // ---------------------------------------------------------------- WebGL
  const VS = `attribute vec3 p; attribute vec3 n; attribute vec3 c; uniform mat4 mvp; uniform mat4 mv;
    varying vec3 vn; varying vec3 vc; varying vec3 vp;
    void main() { gl_Position = mvp * vec4(p, 1.0); vn = mat3(mv) * n; vp = (mv * vec4(p, 1.0)).xyz; vc = c; }`;
  const FS = `precision mediump float; varying vec3 vn; varying vec3 vc; varying vec3 vp;
    void main() {
      vec3 n = normalize(vn); vec3 v = normalize(-vp); if (dot(n, v) < 0.0) n = -n;
      vec3 l1 = normalize(vec3(0.4, 0.6, 1.0)); vec3 l2 = normalize(vec3(-0.6, 0.1, 0.4));
      float d = 0.25 + 0.6 * max(dot(n, l1), 0.0) + 0.25 * max(dot(n, l2), 0.0);
      float s = pow(max(dot(n, normalize(l1 + v)), 0.0), 40.0) * 0.25;
      gl_FragColor = vec4(vc * d + vec3(s), 1.0); }`;
  const PVS = `attribute vec3 p; attribute vec3 c; uniform mat4 mvp; uniform float size; varying vec3 vc;
    void main() { gl_Position = mvp * vec4(p, 1.0); gl_PointSize = size; vc = c; }`;
  const PFS = `precision mediump float; varying vec3 vc;
    void main() { float r = length(gl_PointCoord - vec2(0.5)); if (r > 0.5) discard;
      gl_FragColor = vec4(r > 0.38 ? vec3(0.05) : vc, 1.0); }`;
  function shader(type, src) {
    const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  function program(vs, fs) {
    const p = gl.createProgram();
    gl.attachShader(p, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fs));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    return p;
  }
  function initGL() {
    const canvas = $("gl");
    gl = canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL is not available in this browser");
    const big = nV > 65535;
    if (big && !gl.getExtension("OES_element_index_uint")) throw new Error("this browser lacks 32-bit mesh indices");
    prog = program(VS, FS); pprog = program(PVS, PFS);
    for (const k of ["pos", "nrm", "col", "mpos", "mcol"]) buf[k] = gl.createBuffer();
    buf.idx = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, buf.idx);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, big ? new Uint32Array(tris) : new Uint16Array(tris), gl.STATIC_DRAW);
    buf.idxType = big ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;
  }
  function upload(name, data) { gl.bindBuffer(gl.ARRAY_BUFFER, buf[name]); gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW); }
  function attrib(p, name, b) {
    const loc = gl.getAttribLocation(p, name); if (loc < 0) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, buf[b]); gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
  }
  function matrices() {
    const canvas = gl.canvas, cp = Math.cos(S.pitch);
    const eye = [S.target[0] + S.dist * cp * Math.sin(S.yaw), S.target[1] + S.dist * Math.sin(S.pitch),
                 S.target[2] + S.dist * cp * Math.cos(S.yaw)];
    const view = lookAt(eye, S.target, [0, 1, 0]);
    const proj = perspective(0.6, canvas.width / Math.max(canvas.height, 1), S.dist / 50, S.dist + 4 * S.radius);
    return { view, mvp: mul(proj, view) };
  }
  let dirty = { geom: true, colour: true };
  function draw() {
    const canvas = gl.canvas, dpr = window.devicePixelRatio || 1;
    const w = Math.round(canvas.clientWidth * dpr), h = Math.round(canvas.clientHeight * dpr);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    if (dirty.geom) { framePositions(S.frame); upload("pos", pos); upload("nrm", nrm); upload("mpos", mpos); }
    if (dirty.geom || dirty.colour) { frameColours(S.frame); upload("col", col); upload("mcol", mcol); }
    dirty = { geom: false, colour: false };
    gl.viewport(0, 0, w, h); gl.clearColor(0.11, 0.115, 0.13, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const { view, mvp } = matrices(); S.mvp = mvp;
    gl.enable(gl.DEPTH_TEST); gl.useProgram(prog);
    attrib(prog, "p", "pos"); attrib(prog, "n", "nrm"); attrib(prog, "c", "col");
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "mvp"), false, mvp);
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "mv"), false, view);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, buf.idx);
    gl.drawElements(gl.TRIANGLES, tris.length, buf.idxType, 0);
    for (const k of ["p", "n", "c"]) { const l = gl.getAttribLocation(prog, k); if (l >= 0) gl.disableVertexAttribArray(l); }
    if (S.showMarkers) {
      // Markers stay visible through the skin: a marker behind the lips is still one to look at.
      gl.disable(gl.DEPTH_TEST); gl.useProgram(pprog);
      attrib(pprog, "p", "mpos"); attrib(pprog, "c", "mcol");
      gl.uniformMatrix4fv(gl.getUniformLocation(pprog, "mvp"), false, mvp);
      gl.uniform1f(gl.getUniformLocation(pprog, "size"), 9 * dpr);
      gl.drawArrays(gl.POINTS, 0, nM);
      for (const k of ["p", "c"]) { const l = gl.getAttribLocation(pprog, k); if (l >= 0) gl.disableVertexAttribArray(l); }
    }
  }
  function markerScreen(m) {  // CSS pixels relative to the canvas
    const p = S.mvp, x = mpos[3 * m], y = mpos[3 * m + 1], z = mpos[3 * m + 2];
    const cx = p[0] * x + p[4] * y + p[8] * z + p[12], cy = p[1] * x + p[5] * y + p[9] * z + p[13];
    const cw = p[3] * x + p[7] * y + p[11] * z + p[15];
    const c = gl.canvas;
    return [(cx / cw * 0.5 + 0.5) * c.clientWidth, (1 - (cy / cw * 0.5 + 0.5)) * c.clientHeight];
  }

  // ---------------------------------------------------------------- panels
  function fmt(v) {
    if (v === null || v === undefined || Number.isNaN(v)) return "";
    if (typeof v !== "number") return String(v);
    if (v === 0 || (Math.abs(v) >= 1e-3 && Math.abs(v) < 1e5)) return String(+v.toPrecision(5));
    return v.toExponential(3);
  }
  function diagnostics(f, m) {
    const slot = f * nM + m, row = { marker: META.markers[m], frame: META.frames[f],
                                     status: META.statuses[status[slot]] };
    if (!present[slot]) return row;
    for (const c of diag) row[c.name] = c.kind === "text" ? c.values[c.codes[slot]] : c.codes[slot];
    return row;
  }
  function showMarker() {
    const m = S.pinned >= 0 ? S.pinned : S.hover, el = $("marker");
    if (m < 0) { el.textContent = "hover or click a marker"; return; }
    const row = diagnostics(S.frame, m);
    const rows = Object.entries(row).map(([k, v]) => `<tr><td>${k}</td><td>${esc(fmt(v))}</td></tr>`).join("");
    el.innerHTML = (S.pinned >= 0 ? "<i>pinned (click empty space to unpin)</i>" : "") + `<table>${rows}</table>`;
  }
  function esc(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]); }
  function colourBar() {
    const c = $("cbar"), g = c.getContext("2d"), m = maps[S.map];
    $("colourbar").style.display = m ? "block" : "none";
    if (!m) return;
    g.clearRect(0, 0, c.width, c.height);
    for (let x = 0; x < 200; x++) { const r = ramp(x / 199); g.fillStyle = `rgb(${r.map((v) => Math.round(v * 255))})`; g.fillRect(10 + x, 2, 1, 12); }
    g.fillStyle = "#ddd"; g.font = "11px system-ui, sans-serif"; g.textAlign = "center";
    const short = (v) => String(+v.toPrecision(3));
    g.textAlign = "left"; g.fillText("0 mm", 10, 28);
    g.textAlign = "center"; g.fillText(short(m.vmax_mm / 2), 110, 28);
    g.textAlign = "right"; g.fillText(`>= ${short(m.vmax_mm)} mm`, 210, 28);
    c.title = `${m.label}: ${m.note}; largest ${fmt(m.max_mm)} mm`;
    mapNote();
  }
  // Under the colour bar: what a sparse map shows at this frame (which scan), or that the frame has none, and
  // the colours of its gaps.
  function mapNote() {
    const m = maps[S.map], el = $("cbarNote");
    const swatch = (c) => `<i style="background:rgb(${c.map((v) => Math.round(v * 255))})"></i>`;
    const gaps = (m && m.gaps) ? m.gaps.map((g) => `<span>${swatch(GAP_RGB[g.code])}${esc(g.label)}</span>`).join(" ") : "";
    // A map on every frame (the rig map) only needs the colours of its gaps.
    if (!m || !m.slots) { el.innerHTML = gaps; $("cbar").style.display = "block"; return; }
    const slot = m.slots[S.frame];
    $("cbar").style.display = slot < 0 ? "none" : "block";
    if (slot < 0) {
      const listed = m.pairs.slice(0, 12).map((p) => p.frame).join(", ") + (m.pairs.length > 12 ? ", ..." : "");
      el.innerHTML = `<b>no scan for frame ${META.frames[S.frame]}</b>: ${esc(m.label)} only on the frames ` +
        `compared with one (${esc(listed)}; marked on the curves)`;
      return;
    }
    const p = m.pairs[slot];
    el.innerHTML = `${esc(p.scan)}` + (p.covered_share != null ? `, ${(100 * p.covered_share).toFixed(1)} % covered` : "") +
      (p.rms_mm != null ? `, RMS ${p.rms_mm.toFixed(3)} mm` : "") + "<br>" + gaps;
  }
  function legend() {
    const used = new Set(status);
    $("legend").innerHTML = META.statuses.filter((s, i) => used.has(i)).map((s) => {
      const c = STATUS_RGB[s].map((v) => Math.round(v * 255));
      return `<span><i style="background:rgb(${c})"></i>${s}</span>`;
    }).join("");
  }
  function summary() {
    $("summary").innerHTML = META.summary.map(([k, v]) => `<tr><td>${esc(k)}</td><td>${esc(v)}</td></tr>`).join("") +
      `<tr><td>quantisation</td><td>within ${fmt(META.quantisation.error_bound_mm * 1000)} um, ` +
      `${META.quantisation.moving_vertices} moving vertices</td></tr>` +
      `<tr><td>page load</td><td id="loadTime"></td></tr>`;
    $("warnings").innerHTML = META.warnings.length ? META.warnings.map((w) => `<div class="warn">${esc(w)}</div>`).join("")
      : "none";
  }

  // ---------------------------------------------------------------- curves
  const CURVE_RGB = ["#7cf", "#fa6", "#f77", "#c9f", "#8e8", "#ee7"];
  function drawCurves() {
    const c = $("curves"), dpr = window.devicePixelRatio || 1, g = c.getContext("2d");
    const w = c.clientWidth, h = c.clientHeight;
    if (c.width !== Math.round(w * dpr)) { c.width = Math.round(w * dpr); c.height = Math.round(h * dpr); }
    g.setTransform(dpr, 0, 0, dpr, 0, 0); g.clearRect(0, 0, w, h);
    const list = META.curves, n = Math.max(list.length, 1), rowH = h / n, left = 8, right = w - 8;
    const xOf = (f) => left + (right - left) * (nF > 1 ? f / (nF - 1) : 0.5);
    curves = { xOf, left, right };
    g.font = "11px system-ui, sans-serif";
    list.forEach((cv, i) => {
      const y0 = i * rowH, vals = cv.values.map((v) => (v === null ? NaN : v));
      const fin = vals.filter(Number.isFinite), lo = Math.min(0, ...fin), hi = Math.max(...fin, lo + 1e-9);
      g.strokeStyle = "#333"; g.beginPath(); g.moveTo(0, y0 + rowH - 0.5); g.lineTo(w, y0 + rowH - 0.5); g.stroke();
      const rgb = CURVE_RGB[i % CURVE_RGB.length], yOf = (v) => y0 + rowH - 3 - (rowH - 6) * (v - lo) / (hi - lo);
      if (cv.points) {
        // A few frames far apart (the frames with a scan): dots, as a line between them would invent values.
        g.fillStyle = rgb;
        vals.forEach((v, f) => { if (Number.isFinite(v)) { g.beginPath(); g.arc(xOf(f), yOf(v), 3, 0, 2 * Math.PI); g.fill(); } });
      } else {
        g.strokeStyle = rgb; g.lineWidth = 1.5; g.beginPath();
        let on = false;
        vals.forEach((v, f) => {
          if (!Number.isFinite(v)) { on = false; return; }
          if (on) g.lineTo(xOf(f), yOf(v)); else g.moveTo(xOf(f), yOf(v)); on = true;
        });
        g.stroke();
      }
      const now = vals[S.frame], nowText = Number.isFinite(now) ? fmt(now) : (cv.missing || "");
      const text = `${cv.label} (${cv.unit}): ${nowText}   [max ${fmt(Math.max(...fin))}]`;
      g.fillStyle = "rgba(23, 25, 28, 0.8)"; g.fillRect(left + 1, y0 + 1, g.measureText(text).width + 6, 14);
      g.fillStyle = "#ccc"; g.fillText(text, left + 4, y0 + 12);
    });
    // Marked frames (those compared with a scan): a faint line across the curves and a tick at the bottom.
    for (const mk of META.marks || []) for (const f of mk.frames) {
      g.strokeStyle = "rgba(255, 170, 80, 0.35)"; g.lineWidth = 1; g.beginPath(); g.moveTo(xOf(f), 0); g.lineTo(xOf(f), h); g.stroke();
      g.fillStyle = "#fa5"; g.beginPath(); g.moveTo(xOf(f), h - 7); g.lineTo(xOf(f) - 4, h); g.lineTo(xOf(f) + 4, h); g.fill();
    }
    if (S.loaded < nF) { g.fillStyle = "rgba(0, 0, 0, 0.45)"; g.fillRect(xOf(S.loaded), 0, w - xOf(S.loaded), h); }
    g.strokeStyle = "#fff"; g.lineWidth = 1; g.beginPath(); g.moveTo(xOf(S.frame), 0); g.lineTo(xOf(S.frame), h); g.stroke();
  }

  // ---------------------------------------------------------------- interaction
  function setFrame(f) {
    // Frames still inflating are not there yet: the slider stops at the last one decoded.
    f = Math.max(0, Math.min(S.loaded - 1, Math.round(f)));
    S.frame = f; $("slider").value = f; dirty.geom = true;
    $("frameLabel").textContent = `frame ${META.frames[f]} (${f + 1}/${nF})`;
    if (maps[S.map] && maps[S.map].slots) dirty.colour = true;
    drawCurves(); showMarker(); mapNote(); draw();
  }
  function setMap(key) { S.map = maps[key] ? key : "none"; $("map").value = S.map; dirty.colour = true; colourBar(); draw(); }
  function pick(ev) {
    const r = gl.canvas.getBoundingClientRect(), x = ev.clientX - r.left, y = ev.clientY - r.top;
    let best = -1, bd = 8 * 8;
    if (!S.showMarkers) return -1;
    for (let m = 0; m < nM; m++) { const s = markerScreen(m), d = (s[0] - x) ** 2 + (s[1] - y) ** 2; if (d < bd) { bd = d; best = m; } }
    return best;
  }
  function bind() {
    const slider = $("slider"); slider.max = nF - 1;
    slider.addEventListener("input", () => { S.playing = false; $("play").innerHTML = "&#9654;"; setFrame(+slider.value); });
    $("back").onclick = () => setFrame(S.frame - 1);
    $("fwd").onclick = () => setFrame(S.frame + 1);
    $("play").onclick = () => { S.playing = !S.playing; $("play").innerHTML = S.playing ? "&#10074;&#10074;" : "&#9654;"; S.last = performance.now(); S.acc = 0; };
    $("speed").onchange = (e) => { S.speed = +e.target.value; };
    const sel = $("map");
    for (const m of DATA.maps) { const o = document.createElement("option"); o.value = m.key; o.textContent = m.label; sel.appendChild(o); }
    sel.onchange = (e) => setMap(e.target.value);
    $("showMarkers").onchange = (e) => { S.showMarkers = e.target.checked; draw(); };
    window.addEventListener("keydown", (e) => {
      if (e.target.tagName === "SELECT") return;
      if (e.key === "ArrowLeft") setFrame(S.frame - 1); else if (e.key === "ArrowRight") setFrame(S.frame + 1);
      else if (e.key === " ") { $("play").onclick(); e.preventDefault(); }
    });
    const c = gl.canvas; let drag = null;
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("mousedown", (e) => { drag = { x: e.clientX, y: e.clientY, pan: e.button !== 0 || e.shiftKey, moved: false }; });
    window.addEventListener("mouseup", (e) => {
      if (drag && !drag.moved && e.target === c) { S.pinned = pick(e); showMarker(); }
      drag = null;
    });
    window.addEventListener("mousemove", (e) => {
      if (drag) {
        const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
        if (Math.abs(dx) + Math.abs(dy) > 2) drag.moved = true;
        drag.x = e.clientX; drag.y = e.clientY;
        if (drag.pan) {
          const k = S.dist / c.clientHeight, cy = Math.cos(S.yaw), sy = Math.sin(S.yaw);
          S.target[0] -= k * dx * cy; S.target[2] += k * dx * sy; S.target[1] += k * dy;
        } else { S.yaw -= dx * 0.01; S.pitch = Math.max(-1.5, Math.min(1.5, S.pitch + dy * 0.01)); }
        draw(); return;
      }
      if (e.target !== c) return;
      const m = pick(e), tip = $("tip");
      if (m !== S.hover) { S.hover = m; showMarker(); }
      if (m >= 0) {
        const r = c.getBoundingClientRect();
        tip.style.display = "block"; tip.style.left = `${e.clientX - r.left + 12}px`; tip.style.top = `${e.clientY - r.top + 12}px`;
        tip.textContent = `${META.markers[m]}: ${META.statuses[status[S.frame * nM + m]]}`;
      } else tip.style.display = "none";
    });
    c.addEventListener("wheel", (e) => { S.dist *= Math.exp(e.deltaY * 0.001); S.dist = Math.max(S.radius * 0.2, Math.min(S.radius * 20, S.dist)); draw(); e.preventDefault(); }, { passive: false });
    const cv = $("curves");
    cv.addEventListener("click", (e) => {
      const r = cv.getBoundingClientRect(), x = e.clientX - r.left;
      setFrame((x - curves.left) / (curves.right - curves.left) * (nF - 1));
    });
    window.addEventListener("resize", () => { drawCurves(); draw(); });
  }
  function tick(now) {
    if (S.playing) {
      S.acc += (now - S.last) / 1000 * META.fps * S.speed; S.last = now;
      // Frames are dropped, not slowed, when drawing takes longer than the shot's frame time.
      if (S.acc >= 1) { const step = Math.floor(S.acc); S.acc -= step; setFrame((S.frame + step) % S.loaded); }
    }
    requestAnimationFrame(tick);
  }

  async function main() {
    try {
      if (!META || !DATA) throw new Error("the data scripts review_meta.js / review_frames.js did not load");
      await load();
      initGL(); bind(); legend(); summary(); colourBar();
      document.title = `lgi review: ${META.title}`;
      setFrame(0);
      api.timing.first_frame_ms = performance.now() - (window.LGI_T0 || 0);
      $("loadTime").textContent = `data scripts ${fmt(api.timing.scripts_ms)} ms, decode ${fmt(api.timing.decode_ms)} ms, first frame ${fmt(api.timing.first_frame_ms)} ms`;
      $("status").textContent = META.title;
      Object.assign(api, {
        ready: true, setFrame, setMap, maps: Object.keys(maps), nFrames: nF,
        frame: () => S.frame, markerScreen: (m) => { draw(); return markerScreen(m); },
        statusColour: (s) => STATUS_RGB[s], markerStatus: (f, m) => META.statuses[status[f * nM + m]],
        diagnostics, pinMarker: (m) => { S.pinned = m; showMarker(); },
        // The colour vertex v is given in this frame under the current map (before shading), and the note.
        vertexColour: (v) => Array.from(col.subarray(3 * v, 3 * v + 3)), gapColour: (code) => GAP_RGB[code],
        rampColour: (t) => ramp(t), mapNote: () => $("cbarNote").innerText,
        marked: () => (META.marks || []).map((mk) => mk.frames),
      });
      S.last = performance.now(); requestAnimationFrame(tick);
      await loadRest();
    } catch (err) {
      api.error = String(err && err.message || err);
      $("status").textContent = `cannot show the shot: ${api.error}`;
      console.error(err);
    }
  }
  main();
})();
