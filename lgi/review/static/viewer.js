// lgi shot review viewer: one shaded mesh with per-vertex colours, markers as points, an orbit camera, per-frame
// curves. Plain WebGL 1 and 2D canvas, written for lgi. It reads the data scripts beside it, review_meta.js and
// review_frames.js, then frames/overview.html (every Nth frame) and the frames themselves from
// frames/block_NNNNN.html, which it frames when the cursor comes near them and drops far from it. It fetches nothing (Chromium refuses
// fetch on file://, not scripts or frames), so the page works from file:// with no server and no network, and a
// long take costs the browser the blocks around the cursor, not the take.
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
    const T = TYPES[b.dtype];
    if (b.gzip) {
      // The browser's own gzip, over a stream (not a fetch, so file:// does not matter), read into an array of the
      // size the shape gives: a third faster than collecting the stream through a Response.
      const n = b.shape.reduce((x, y) => x * y, 1) * T.BYTES_PER_ELEMENT, out = new Uint8Array(n);
      const ds = new DecompressionStream("gzip"), w = ds.writable.getWriter();
      w.write(bytes); w.close();
      const rd = ds.readable.getReader();
      let off = 0;
      for (;;) {
        const { value, done } = await rd.read();
        if (done) break;
        if (off + value.length > n) throw new Error("a data blob inflates past its shape");
        out.set(value, off); off += value.length;
      }
      if (off !== n) throw new Error("a data blob inflates short of its shape");
      bytes = out;
    }
    return new T(bytes.buffer, bytes.byteOffset, bytes.byteLength / T.BYTES_PER_ELEMENT);
  }

  // Text that repeats (a block's diagnostics' shape lists) comes as gzip-compressed JSON.
  async function decodeJSON(b) { return JSON.parse(new TextDecoder().decode(await decode(b))); }

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
  // Blocks kept decoded: the cursor's, BEHIND before it and AHEAD after it in the direction of play (loaded in that
  // order, PARALLEL at a time), and up to KEEP in all (the nearest stay, so scrubbing back and forth does not
  // reload them). KEEP bounds the page's memory however long the shot: 12 blocks of 8 ICT frames with a colour map
  // are about 14 MB decoded.
  const AHEAD = 4, BEHIND = 2, KEEP = 12, PARALLEL = 2;
  const S = { frame: 0, dir: 1, playing: false, speed: 1, map: "none", showMarkers: true, yaw: 0, pitch: 0, dist: 1,
              target: [0, 0, 0], radius: 1, hover: -1, pinned: -1, acc: 0, last: 0, shown: null };
  let nF, nV, nM, nK, tris, rest, moving, scale, status, maps = {}, mv, mw, OV, curveData = [];
  let pos, nrm, col, mpos, mcol, gl, prog, pprog, buf = {}, curves;
  const blocks = new Map();  // block index -> {k, lo, codes, maps, present, diag, bytes, ready, started, promise}
  let inflight = 0;

  async function load() {
    const t0 = performance.now();
    nF = DATA.n_frames; nV = META.n_vertices; nM = META.markers.length;
    const ovFile = loadFile("overview", DATA.overview);
    [tris, rest, moving, mv, mw, status] = await Promise.all([
      decode(META.triangles), decode(DATA.rest), decode(DATA.moving),
      decode(META.marker_vertices), decode(META.marker_weights), decode(META.status)]);
    const ov = await ovFile;
    nK = moving.length; scale = DATA.scale;
    // The overview: every Nth frame, whole, for the rough mesh while a frame's block loads.
    const ovMaps = {};
    const [ovCodes, ...ovMapBytes] = await Promise.all([decode(ov.codes), ...DATA.maps.map((m) => (ov.maps[m.key] ? decode(ov.maps[m.key]) : null))]);
    DATA.maps.forEach((m, i) => { if (ovMapBytes[i]) ovMaps[m.key] = ovMapBytes[i]; });
    OV = { frames: ov.frames, codes: deltaPlanes(ovCodes, nK * 3), maps: ovMaps };
    for (const m of DATA.maps) {
      const mm = { ...m, top: m.top || 255 };
      mm.lut = lut(mm.top);
      // A map with slots (the scan map: a few frames) comes whole with the header; the others come by block.
      if (m.slots) mm.values = await decode(m.values);
      maps[m.key] = mm;
    }
    curveData = await Promise.all(META.curves.map(async (c) => ({ ...c, values: await decode(c.values) })));
    // The header's blobs are decoded: let their base64 text go.
    for (const k of ["rest", "moving"]) delete DATA[k];
    for (const m of DATA.maps) delete m.values;
    delete META.triangles; delete META.status;
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

  // ---------------------------------------------------------------- blocks
  const blockOf = (f) => Math.floor(f / DATA.block);
  const nBlocks = () => DATA.files.length;
  // A block file is a small HTML page holding its block as JSON (not a script: Chromium's compilation cache keeps
  // the source of every script a page has run, so a long take scrubbed through in block scripts would stay in
  // memory whole). The page frames it in a hidden iframe, which posts the text back; the frame is then removed and
  // the block's page freed. A frame that loads without handing over a block (a missing file shows the browser's
  // error page) fails after a grace period.
  const framing = new Map();  // iframe -> { k, resolve, reject }
  window.addEventListener("message", (e) => {
    const text = e.data && e.data.lgiReviewBlock;
    if (typeof text !== "string") return;
    for (const [f, p] of framing) {
      if (f.contentWindow !== e.source) continue;
      framing.delete(f); f.remove();
      let data;
      try { data = JSON.parse(text); } catch (err) { p.reject(err); return; }
      if (data.block !== p.k) p.reject(new Error(`${p.url} holds block ${data.block}, not ${p.k}`));
      else p.resolve(data);
      return;
    }
  });
  // Block k (or "overview") from the page at url.
  function loadFile(k, url) {
    return new Promise((resolve, reject) => {
      const f = document.createElement("iframe");
      f.style.display = "none"; f.setAttribute("aria-hidden", "true"); f.src = url;
      framing.set(f, { k, url, resolve, reject });
      f.onload = () => setTimeout(() => {
        if (!framing.has(f)) return;
        framing.delete(f); f.remove();
        reject(new Error(`cannot load ${url} (is the frames folder beside the page?)`));
      }, 2000);
      document.body.appendChild(f);
    });
  }
  async function decodeBlock(b, data) {
    const keys = Object.keys(data.maps);
    const [c, present, ...rest_] = await Promise.all([decode(data.codes), decode(data.present),
      ...keys.map((k) => decode(data.maps[k])), ...data.diagnostics.map((d) => decode(d.data)),
      ...data.diagnostics.map((d) => (d.kind === "text" ? decodeJSON(d.values) : null))]);
    const nd = data.diagnostics.length, mapVals = rest_.slice(0, keys.length);
    const dcodes = rest_.slice(keys.length, keys.length + nd), dvals = rest_.slice(keys.length + nd);
    b.codes = deltaPlanes(c, nK * 3); b.present = present; b.maps = {};
    keys.forEach((k, i) => { b.maps[k] = mapVals[i]; });
    b.diag = data.diagnostics.map((d, i) => ({ name: d.name, kind: d.kind, values: dvals[i], codes: dcodes[i] }));
    b.bytes = b.codes.byteLength + present.byteLength + mapVals.reduce((s, a) => s + a.byteLength, 0) +
      dcodes.reduce((s, a) => s + a.byteLength, 0);
    b.ready = true;
  }
  // The blocks the cursor wants, most urgent first.
  function wanted() {
    const c = blockOf(S.frame), out = [c];
    for (let i = 1; i <= AHEAD; i++) out.push(c + i * S.dir);
    for (let i = 1; i <= BEHIND; i++) out.push(c - i * S.dir);
    return out.filter((k) => k >= 0 && k < nBlocks());
  }
  function request(k) {
    let b = blocks.get(k);
    if (b) return b;
    b = { k, lo: k * DATA.block, ready: false, started: false };
    b.promise = new Promise((resolve, reject) => { b.start = () => {
      b.started = true; inflight++;
      // After the current task: the frame asked for is drawn (from the overview) before a frame is added.
      setTimeout(() => loadFile(k, DATA.files[k]).then((data) => decodeBlock(b, data)).then(() => {
        inflight--; resolve(b); arrived(b);
      }, (err) => { inflight--; blocks.delete(k); reject(err); fail(err); }), 0);
    }; });
    b.promise.catch(() => {});
    blocks.set(k, b);
    return b;
  }
  // Start what the cursor wants (PARALLEL at a time), and drop what it no longer does beyond KEEP blocks, the
  // farthest first: a block not yet started is dropped at once.
  function schedule() {
    const want = wanted();
    if (!want.length) return;  // a shot without frames
    for (const k of want) request(k);
    for (const [k, b] of blocks) if (!b.started && !want.includes(k)) blocks.delete(k);
    // While the cursor's own block is missing it loads alone: on two cores a second load would halve its speed.
    const own = blocks.get(want[0]);
    for (const k of own.ready ? want : want.slice(0, 1)) {
      const b = blocks.get(k); if (inflight < PARALLEL && !b.started) b.start();
    }
    const c = blockOf(S.frame), held = [...blocks.values()].filter((b) => b.ready);
    if (held.length > KEEP) {
      held.sort((a, b) => Math.abs(b.k - c) - Math.abs(a.k - c));
      for (const b of held.slice(0, held.length - KEEP)) if (!want.includes(b.k)) blocks.delete(b.k);
    }
  }
  function arrived(b) {
    api.timing.blocks_loaded = (api.timing.blocks_loaded || 0) + 1;
    if (blockOf(S.frame) === b.k) { dirty.geom = true; dirty.colour = true; showFrame(); }
    schedule();
    drawCurves();
  }
  function fail(err) {
    api.error = String(err && err.message || err);
    $("status").textContent = `cannot show the shot: ${api.error}`;
    console.error(err);
  }
  // Where frame f's data is now: its block when loaded, else the overview's nearest frame (positions and maps of
  // that frame; the markers' statuses are always the frame's own).
  function source(f) {
    const b = blocks.get(blockOf(f));
    if (b && b.ready) return { exact: true, shown: f, row: f - b.lo, codes: b.codes, maps: b.maps, block: b };
    const ovStride = OV.frames.length > 1 ? OV.frames[1] : 1;
    const j = Math.min(OV.frames.length - 1, Math.round(f / ovStride));
    return { exact: OV.frames[j] === f, shown: OV.frames[j], row: j, codes: OV.codes, maps: OV.maps, block: null };
  }

  // ---------------------------------------------------------------- per frame
  function framePositions(src) {
    pos.set(rest);
    const n = nK, c0 = src.row * n * 3, codes = src.codes;
    for (let i = 0; i < n; i++) {
      const v = 3 * moving[i], c = c0 + 3 * i;
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
  // A map's codes at frame f from src, with their row, or null where it has none (a frame without a scan).
  function mapRow(m, f, src) {
    if (!m) return null;
    if (m.slots) return m.slots[f] >= 0 ? { vals: m.values, base: m.slots[f] * nV } : null;
    const vals = src.maps[m.key];
    return vals ? { vals, base: src.row * nV } : null;
  }
  function frameColours(f, src) {
    const m = maps[S.map], r = mapRow(m, f, src);
    if (!r) { for (let i = 0; i < nV * 3; i += 3) col.set(SHADED, i); }
    else {
      const vals = r.vals, base = r.base, L = m.lut;
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
    if (dirty.geom || dirty.colour) {
      const src = source(S.frame);
      S.shown = { frame: S.frame, at: src.shown, exact: src.exact };
      if (dirty.geom) { framePositions(src); upload("pos", pos); upload("nrm", nrm); upload("mpos", mpos); }
      frameColours(S.frame, src); upload("col", col); upload("mcol", mcol);
    }
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
    const row = { marker: META.markers[m], frame: META.frames[f], status: META.statuses[status[f * nM + m]] };
    const b = blocks.get(blockOf(f));
    if (!b || !b.ready) { row.diagnostics = "loading with the frame's block"; return row; }
    const slot = (f - b.lo) * nM + m;
    if (!b.present[slot]) return row;
    for (const c of b.diag) row[c.name] = c.kind === "text" ? c.values[c.codes[slot]] : c.codes[slot];
    return row;
  }
  function showMarker() {
    const m = S.pinned >= 0 ? S.pinned : S.hover, el = $("marker");
    if (m < 0) { el.textContent = "hover or click a marker"; return; }
    const row = diagnostics(S.frame, m);
    const rows = Object.entries(row).map(([k, v]) => `<tr><td>${esc(k)}</td><td>${esc(fmt(v))}</td></tr>`).join("");
    el.innerHTML = (S.pinned >= 0 ? "<i>pinned (click empty space to unpin)</i>" : "") + `<table>${rows}</table>`;
  }
  function esc(s) { return String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]); }
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
    const used = new Set();
    for (let i = 0; i < status.length; i++) used.add(status[i]);
    $("legend").innerHTML = META.statuses.filter((s, i) => used.has(i)).map((s) => {
      const c = STATUS_RGB[s].map((v) => Math.round(v * 255));
      return `<span><i style="background:rgb(${c})"></i>${esc(s)}</span>`;
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
  // The curves are drawn once per size into a canvas of their own (a long take's 36,000 frames decimated to each
  // pixel column's lowest and highest value, which is the picture the whole line gives); a frame change only
  // copies it and draws the cursor, the values and the blocks held.
  const CURVE_RGB = ["#7cf", "#fa6", "#f77", "#c9f", "#8e8", "#ee7"];
  let curveBg = null;
  function curveLayout() {
    const c = $("curves"), w = c.clientWidth, h = c.clientHeight, left = 8, right = w - 8;
    const xOf = (f) => left + (right - left) * (nF > 1 ? f / (nF - 1) : 0.5);
    return { w, h, left, right, xOf, rowH: h / Math.max(curveData.length, 1) };
  }
  function renderCurves(L, dpr) {
    const bg = document.createElement("canvas");
    bg.width = Math.round(L.w * dpr); bg.height = Math.round(L.h * dpr);
    const g = bg.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    const cols = Math.max(1, Math.round(L.right - L.left));
    curveData.forEach((cv, i) => {
      const y0 = i * L.rowH, vals = cv.values;
      let lo = 0, hi = -Infinity;
      for (let f = 0; f < vals.length; f++) { const v = vals[f]; if (v === v) { if (v < lo) lo = v; if (v > hi) hi = v; } }
      cv.max = hi; if (!(hi > lo)) hi = lo + 1e-9;
      g.strokeStyle = "#333"; g.beginPath(); g.moveTo(0, y0 + L.rowH - 0.5); g.lineTo(L.w, y0 + L.rowH - 0.5); g.stroke();
      const rgb = CURVE_RGB[i % CURVE_RGB.length], yOf = (v) => y0 + L.rowH - 3 - (L.rowH - 6) * (v - lo) / (hi - lo);
      if (cv.points) {
        // A few frames far apart (the frames with a scan): dots, as a line between them would invent values.
        g.fillStyle = rgb;
        for (let f = 0; f < vals.length; f++) if (vals[f] === vals[f]) { g.beginPath(); g.arc(L.xOf(f), yOf(vals[f]), 3, 0, 2 * Math.PI); g.fill(); }
        return;
      }
      g.strokeStyle = rgb; g.lineWidth = 1.5; g.beginPath();
      let on = false;
      if (vals.length <= 2 * cols) {
        for (let f = 0; f < vals.length; f++) {
          const v = vals[f];
          if (v !== v) { on = false; continue; }
          if (on) g.lineTo(L.xOf(f), yOf(v)); else g.moveTo(L.xOf(f), yOf(v)); on = true;
        }
      } else {
        // Per pixel column: from its lowest to its highest value, joined to the next column.
        let col_ = -1, cmin = Infinity, cmax = -Infinity;
        const flush = () => {
          if (col_ < 0) return;
          if (cmin === Infinity) { on = false; return; }
          const x = L.left + col_ + 0.5;
          if (on) g.lineTo(x, yOf(cmin)); else g.moveTo(x, yOf(cmin));
          g.lineTo(x, yOf(cmax)); on = true;
        };
        for (let f = 0; f < vals.length; f++) {
          const c = Math.min(cols - 1, Math.floor((L.xOf(f) - L.left)));
          if (c !== col_) { flush(); col_ = c; cmin = Infinity; cmax = -Infinity; }
          const v = vals[f]; if (v === v) { if (v < cmin) cmin = v; if (v > cmax) cmax = v; }
        }
        flush();
      }
      g.stroke();
    });
    // Marked frames (those compared with a scan): a faint line across the curves and a tick at the bottom.
    for (const mk of META.marks || []) for (const f of mk.frames) {
      const x = L.xOf(f);
      g.strokeStyle = "rgba(255, 170, 80, 0.35)"; g.lineWidth = 1; g.beginPath(); g.moveTo(x, 0); g.lineTo(x, L.h); g.stroke();
      g.fillStyle = "#fa5"; g.beginPath(); g.moveTo(x, L.h - 7); g.lineTo(x - 4, L.h); g.lineTo(x + 4, L.h); g.fill();
    }
    return bg;
  }
  function drawCurves() {
    const c = $("curves"), dpr = window.devicePixelRatio || 1, g = c.getContext("2d"), L = curveLayout();
    if (c.width !== Math.round(L.w * dpr) || c.height !== Math.round(L.h * dpr) || !curveBg) {
      c.width = Math.round(L.w * dpr); c.height = Math.round(L.h * dpr);
      curveBg = renderCurves(L, dpr);
    }
    curves = L;
    g.setTransform(1, 0, 0, 1, 0, 0); g.clearRect(0, 0, c.width, c.height); g.drawImage(curveBg, 0, 0);
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.font = "11px system-ui, sans-serif";
    curveData.forEach((cv, i) => {
      const now = cv.values[S.frame], nowText = now === now ? fmt(now) : (cv.missing || "");
      const text = `${cv.label} (${cv.unit}): ${nowText}   [max ${fmt(cv.max)}]`;
      g.fillStyle = "rgba(23, 25, 28, 0.8)"; g.fillRect(L.left + 1, i * L.rowH + 1, g.measureText(text).width + 6, 14);
      g.fillStyle = "#ccc"; g.fillText(text, L.left + 4, i * L.rowH + 12);
    });
    // The blocks held decoded, as a strip at the bottom.
    g.fillStyle = "rgba(120, 200, 255, 0.5)";
    for (const b of blocks.values()) if (b.ready) {
      const x0 = L.xOf(b.lo), x1 = L.xOf(Math.min(nF - 1, b.lo + DATA.block - 1));
      g.fillRect(x0, L.h - 3, Math.max(1, x1 - x0), 3);
    }
    g.strokeStyle = "#fff"; g.lineWidth = 1; g.beginPath(); g.moveTo(L.xOf(S.frame), 0); g.lineTo(L.xOf(S.frame), L.h); g.stroke();
  }

  // ---------------------------------------------------------------- interaction
  // Show the cursor's frame: the full frame when its block is there, else the overview's nearest frame at once.
  function showFrame() {
    draw();
    const sh = S.shown, f = S.frame;
    $("frameLabel").textContent = `frame ${META.frames[f]} (${f + 1}/${nF})` + (sh && !sh.exact ? " ~" : "");
    $("status").textContent = sh && !sh.exact ? `${META.title}: frame ${META.frames[f]} loading, the overview's ` +
      `frame ${META.frames[sh.at]} meanwhile` : META.title;
    showMarker();
  }
  // Resolves when the cursor's frame is drawn in full (at once when its block is there).
  function setFrame(f) {
    f = Math.max(0, Math.min(nF - 1, Math.round(f)));
    if (f !== S.frame) S.dir = f < S.frame && f > S.frame - DATA.block ? -1 : 1;
    S.frame = f; $("slider").value = f; dirty.geom = true; dirty.colour = true;
    schedule();
    showFrame(); mapNote(); drawCurves();
    const b = blocks.get(blockOf(f));
    return b ? b.promise.then(() => undefined) : Promise.resolve();
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
    window.addEventListener("resize", () => { curveBg = null; drawCurves(); draw(); });
  }
  function tick(now) {
    if (S.playing) {
      S.acc += (now - S.last) / 1000 * META.fps * S.speed; S.last = now;
      // Frames are dropped, not slowed, when drawing takes longer than the shot's frame time.
      if (S.acc >= 1) { const step = Math.floor(S.acc); S.acc -= step; S.dir = 1; setFrame((S.frame + step) % nF); }
    }
    requestAnimationFrame(tick);
  }

  async function main() {
    try {
      if (!META || !DATA) throw new Error("the data scripts review_meta.js / review_frames.js did not load");
      if (!DATA.files) throw new Error("review_frames.js is of an older lgi review: write the page again");
      await load();
      initGL(); bind(); legend(); summary(); colourBar();
      document.title = `lgi review: ${META.title}`;
      const first = setFrame(0);
      api.timing.first_frame_ms = performance.now() - (window.LGI_T0 || 0);
      $("loadTime").textContent = `data scripts ${fmt(api.timing.scripts_ms)} ms, decode ${fmt(api.timing.decode_ms)} ms, first frame ${fmt(api.timing.first_frame_ms)} ms`;
      Object.assign(api, {
        ready: true, setFrame, setMap, maps: Object.keys(maps), nFrames: nF, block: DATA.block,
        overviewFrames: OV.frames.slice(),
        frame: () => S.frame, markerScreen: (m) => { draw(); return markerScreen(m); },
        statusColour: (s) => STATUS_RGB[s], markerStatus: (f, m) => META.statuses[status[f * nM + m]],
        diagnostics, pinMarker: (m) => { S.pinned = m; showMarker(); },
        // The colour vertex v is given in this frame under the current map (before shading), and the note.
        vertexColour: (v) => Array.from(col.subarray(3 * v, 3 * v + 3)), gapColour: (code) => GAP_RGB[code],
        rampColour: (t) => ramp(t), mapNote: () => $("cbarNote").innerText,
        marked: () => (META.marks || []).map((mk) => mk.frames),
        // What is drawn: the frame, the frame whose data it is (the overview's while the block loads), exact.
        shown: () => ({ ...S.shown }), positions: () => Array.from(pos),
        blocksHeld: () => [...blocks.values()].filter((b) => b.ready).map((b) => b.k).sort((a, b) => a - b),
        bytesHeld: () => [...blocks.values()].reduce((s, b) => s + (b.bytes || 0), 0),
        // Draw and wait for the GPU (for timing a step).
        finish: () => { draw(); gl.finish(); },
      });
      // Idle: the cursor's frame is drawn in full and no block is loading.
      Object.defineProperty(api, "idle", { get: () => api.ready && !!S.shown && S.shown.exact && inflight === 0 });
      S.last = performance.now(); requestAnimationFrame(tick);
      await first;
      api.timing.first_block_ms = performance.now() - (window.LGI_T0 || 0);
      $("loadTime").textContent += `, first block ${fmt(api.timing.first_block_ms)} ms`;
    } catch (err) {
      fail(err);
    }
  }
  main();
})();
