// Pilot station page: chase view drawn by hand on a 2D canvas from /sim/scene + /odom, camera inset,
// keyboard -> WebSocket (held keys), connection / assistant / landing state, the assistant's intent cues
// (goal pad highlight in the chase view and the inset, descent light, push arrow). No external assets.
'use strict';
(function () {
  const KEYS = ['KeyW', 'KeyS', 'KeyA', 'KeyD', 'ArrowUp', 'ArrowDown', 'Space'];
  // key -> [axis in base_link FLU, sign]: the same bindings as teleop_keyboard
  const AXES = { KeyW: [0, 1], KeyS: [0, -1], KeyA: [1, 1], KeyD: [1, -1], ArrowUp: [2, 1], ArrowDown: [2, -1] };
  const HEARTBEAT_MS = 250;      // resend the held set (the station releases keys not refreshed for 1 s)
  const MOTION_MPS = 0.15;       // "the vehicle moves": body velocity along the key's axis above this
  const NEAR = 0.05;
  const MIN_W = 480, MIN_H = 360;
  // intent cues: the goal pad the assistant believes in (sure: filled, unsure: outlined, unknown: grey)
  const CUE_STYLE = {
    sure: { fill: 'rgba(0,220,255,0.55)', stroke: '#00dcff', width: 4, dash: [] },
    unsure: { fill: null, stroke: '#00dcff', width: 3, dash: [10, 7] },
    unknown: { fill: 'rgba(165,165,165,0.6)', stroke: '#a5a5a5', width: 3, dash: [6, 6] },
  };
  const PUSH_COLOUR = '#ff3cf0';
  const PUSH_M_PER_MPS = 1.0;    // arrow length in the chase view per m/s of push
  const PUSH_MIN_MPS = 0.05;     // smaller pushes are not drawn
  const RING_M = 0.4;            // goal cue radius where no pad box is known (no scene)

  const stats = window.stationStats = {
    frames: 0, fps: 0, ws: 'connecting', role: null, mode: null, states: 0, cameraFrames: 0, errors: 0,
    acks: 0, ackRttMs: null, keyToMotionMs: [], releases: 0, held: [], canvas: null, landing: null,
    scenePlatforms: 0, goal: null, pose: null, cues: null,
    cueDrawn: { goal: null, push: null, descent: null },   // what the last frame drew of the cues (screen px)
  };

  const view = document.getElementById('view');
  const ctx = view.getContext('2d');
  const inset = document.getElementById('inset');
  const ictx = inset.getContext('2d');
  const camBuf = document.createElement('canvas');
  const el = (id) => document.getElementById(id);

  let ws = null, reconnectMs = 500, seq = 0;
  // the pilot's session token: a reconnecting (or reloaded) pilot page presents it to keep the pilot role
  const SESSION_KEY = 'stationSession';
  const storage = { get() { try { return sessionStorage.getItem(SESSION_KEY); } catch (err) { return null; } },
    set(v) { try { if (v) sessionStorage.setItem(SESSION_KEY, v); else sessionStorage.removeItem(SESSION_KEY); } catch (err) { /* no storage */ } } };
  let session = storage.get();
  let held = [];
  const sentAt = new Map();
  let motionProbe = null;
  let cfg = { mode: 'practice', show_goal: true, chase: { back_m: 3.5, up_m: 2.0, fov_deg: 60 },
    camera_geom: { vfov_deg: 58, offset_m: 0.05 } };
  let scene = { platforms: [], goal: null };
  let state = null, stateAt = 0;
  let landingTimer = null;

  // ------------------------------------------------------------------ keyboard
  // the study panel (study.js) sends its steps through the station's socket
  window.stationSend = (obj) => {
    if (!ws || ws.readyState !== WebSocket.OPEN) return false;
    ws.send(JSON.stringify(obj));
    return true;
  };
  function sendKeys() {
    if (!ws || ws.readyState !== WebSocket.OPEN) return;
    seq += 1;
    sentAt.set(seq, performance.now());
    if (sentAt.size > 64) sentAt.delete(sentAt.keys().next().value);
    ws.send(JSON.stringify({ type: 'keys', down: held.slice(), seq: seq }));
  }
  function setHeld(next) {
    const changed = next.length !== held.length || next.some((k, i) => k !== held[i]);
    held = next;
    stats.held = held.slice();
    for (const s of document.querySelectorAll('#keys span')) s.classList.toggle('down', held.includes(s.dataset.code));
    if (changed) sendKeys();
  }
  function releaseAll(why) {
    if (held.length) stats.releases += 1;
    motionProbe = null;
    setHeld([]);
    stats.lastRelease = why;
  }
  // keys typed into the study panel's forms (participant ID, answers) are not flight keys
  const inForm = (e) => e.target && e.target.closest && e.target.closest('#study');
  window.addEventListener('keydown', (e) => {
    if (!KEYS.includes(e.code) || inForm(e)) return;
    e.preventDefault();
    if (held.includes(e.code)) return;                 // auto-repeat: nothing new
    stats.lastKey = { code: e.code, epochMs: performance.timeOrigin + e.timeStamp };   // for latency benches
    if (e.code === 'Space') { setHeld(['Space']); motionProbe = null; return; }
    const ax = AXES[e.code];
    const v = state && state.pose ? state.pose.v[ax[0]] * ax[1] : 0;
    if (v < 0.05) motionProbe = { t: e.timeStamp, code: e.code, axis: ax[0], sign: ax[1] };
    setHeld(held.filter((k) => k !== e.code && k !== 'Space').concat([e.code]));
  });
  window.addEventListener('keyup', (e) => {
    if (!KEYS.includes(e.code) || inForm(e)) return;
    e.preventDefault();
    if (motionProbe && motionProbe.code === e.code) motionProbe = null;
    setHeld(held.filter((k) => k !== e.code));
  });
  window.addEventListener('blur', () => releaseAll('blur'));
  window.addEventListener('pagehide', () => releaseAll('pagehide'));
  document.addEventListener('visibilitychange', () => { if (document.hidden) releaseAll('hidden'); });
  setInterval(sendKeys, HEARTBEAT_MS);

  // ------------------------------------------------------------------ socket
  function setConn(text, cls) {
    const c = el('conn');
    c.textContent = text;
    c.className = 'pill ' + cls;
  }
  function connect() {
    const proto = location.protocol === 'https:' ? 'wss:' : 'ws:';
    ws = new WebSocket(proto + '//' + location.host + '/ws' + (session ? '?session=' + encodeURIComponent(session) : ''));
    ws.binaryType = 'arraybuffer';
    stats.ws = 'connecting';
    ws.onopen = () => { stats.ws = 'open'; reconnectMs = 500; setConn('connected', 'ok'); sendKeys(); };
    ws.onclose = () => {
      stats.ws = 'closed';
      held = []; stats.held = []; motionProbe = null;
      for (const s of document.querySelectorAll('#keys span')) s.classList.remove('down');
      setConn('disconnected - reconnecting', 'bad');
      setTimeout(connect, reconnectMs);
      reconnectMs = Math.min(5000, reconnectMs * 2);
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data !== 'string') { onCamera(ev.data); return; }
      let msg;
      try { msg = JSON.parse(ev.data); } catch (err) { stats.errors += 1; return; }
      if (msg.type === 'state') onState(msg);
      else if (msg.type === 'scene') onScene(msg);
      else if (msg.type === 'hello') onHello(msg);
      else if (msg.type === 'landing') onLanding(msg);
      else if (typeof msg.type === 'string' && msg.type.startsWith('study')) {
        if (msg.type === 'study') stats.study = msg;
        if (window.stationStudy) window.stationStudy.onMessage(msg);
      }
      else if (msg.type === 'ack') {
        const t0 = sentAt.get(msg.seq);
        if (t0 !== undefined) { stats.ackRttMs = performance.now() - t0; sentAt.delete(msg.seq); }
        stats.acks += 1;
      } else if (msg.type === 'error') { stats.errors += 1; console.warn('station:', msg.message); }
    };
  }
  function onHello(msg) {
    cfg = msg;
    session = msg.role === 'pilot' && msg.session ? msg.session : null;   // a view-only page holds no token
    storage.set(session);
    stats.role = msg.role; stats.mode = msg.mode; stats.speed = msg.speed; stats.speedZ = msg.speed_z;
    stats.chase = msg.chase; stats.cameraGeom = msg.camera_geom || null;
    el('role').textContent = msg.role === 'pilot' ? 'you are the pilot' : 'view only';
    el('role').className = 'pill ' + (msg.role === 'pilot' ? 'ok' : 'warn');
    el('mode').textContent = { practice: 'practice', study: 'study', free: 'free flight' }[msg.mode] || msg.mode;
    const b = el('banner');
    if (msg.role !== 'pilot') { b.textContent = msg.reason || 'Another pilot is connected: view only.'; b.className = ''; }
    else b.className = 'hidden';
    inset.style.display = msg.camera ? '' : 'none';
  }
  function onScene(msg) {
    scene = msg;
    stats.scenePlatforms = msg.platforms.length; stats.goal = msg.goal; stats.scene = msg;
  }
  function onLanding(msg) {
    stats.landing = msg;
    const box = el('landing');
    box.textContent = msg.text;
    box.className = msg.show ? (msg.success ? 'success' : 'fail') : '';
    clearTimeout(landingTimer);
    landingTimer = setTimeout(() => { box.className = 'hidden'; }, msg.show ? 5000 : 2000);
  }
  function onState(msg) {
    state = msg; stateAt = performance.now();
    stats.states += 1; stats.pose = msg.pose;
    const a = el('assist');
    const assist = { off: ['unassisted', ''], standby: ['assisted', 'ok'], acting: ['assistant acting', 'acting'] };
    const [txt, cls] = assist[msg.assist] || ['assistant: ?', ''];
    a.textContent = txt; a.className = 'pill ' + cls;
    stats.cues = msg.cues || null;
    showDescent(stats.cues ? stats.cues.descent : null);
    if (ws && ws.readyState === WebSocket.OPEN) {
      if (!msg.pose || msg.odom_age_s === null || msg.odom_age_s > 1.0) setConn('connected - no vehicle data', 'warn');
      else setConn('connected', 'ok');
    }
    if (motionProbe && msg.pose) {
      const v = msg.pose.v[motionProbe.axis] * motionProbe.sign;
      if (v > MOTION_MPS) {
        stats.keyToMotionMs.push(performance.now() - motionProbe.t);
        motionProbe = null;
      }
    }
    if (msg.pose) {
      const p = msg.pose.p, v = msg.pose.v;
      const ground = surfaceBelow(p[0], p[1]);
      el('telemetry').textContent =
        `height ${(p[2] - ground).toFixed(2)} m   alt ${p[2].toFixed(2)} m\n` +
        `v ${v[0].toFixed(2)} ${v[1].toFixed(2)} ${v[2].toFixed(2)} m/s   cmd ${msg.cmd.map((x) => x.toFixed(1)).join(' ')}`;
    } else el('telemetry').textContent = 'waiting for /odom';
    if (msg.stopped) el('telemetry').textContent += '\nSTOP held by a view-only page';
    stats.stopped = !!msg.stopped;
  }
  function showDescent(d) {
    const box = el('descent');
    const look = { ok: ['descend', 'go'], hold: ['hold', 'stop'], unknown: ['descend ?', 'unknown'] }[d];
    stats.cueDrawn.descent = look ? d : null;
    if (!look) { box.className = 'hidden'; return; }
    box.className = look[1];
    box.querySelector('.label').textContent = look[0];
  }
  function onCamera(buf) {
    const dv = new DataView(buf);
    if (buf.byteLength < 4) return;
    const w = dv.getUint16(0, true), h = dv.getUint16(2, true);
    if (w === 0 || h === 0 || buf.byteLength !== 4 + w * h * 3) { stats.errors += 1; return; }
    const rgb = new Uint8Array(buf, 4);
    const img = new ImageData(w, h);
    for (let i = 0, j = 0; i < w * h; i += 1, j += 3) {
      img.data[4 * i] = rgb[j]; img.data[4 * i + 1] = rgb[j + 1]; img.data[4 * i + 2] = rgb[j + 2]; img.data[4 * i + 3] = 255;
    }
    camBuf.width = w; camBuf.height = h;
    camBuf.getContext('2d').putImageData(img, 0, 0);
    stats.cameraFrames += 1;
  }

  // ------------------------------------------------------------------ 3D helpers
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const scl = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const n = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };
  function rotate(q, v) {           // quaternion (x, y, z, w) applied to v
    const [x, y, z, w] = q;
    const u = [x, y, z];
    const t = scl(cross(u, v), 2);
    return add(add(v, scl(t, w)), cross(u, t));
  }
  const yawOf = (q) => Math.atan2(2 * (q[3] * q[2] + q[0] * q[1]), 1 - 2 * (q[1] * q[1] + q[2] * q[2]));

  function surfaceBelow(x, y) {
    let h = 0;
    for (const b of scene.platforms) {
      const d = rotate([-b.q[0], -b.q[1], -b.q[2], b.q[3]], [x - b.p[0], y - b.p[1], 0]);
      if (Math.abs(d[0]) <= b.s[0] / 2 && Math.abs(d[1]) <= b.s[1] / 2) h = Math.max(h, b.p[2] + b.s[2] / 2);
    }
    return h;
  }

  function makeCamera(pos, yaw, W, H) {
    const f = [Math.cos(yaw), Math.sin(yaw), 0];
    const eye = add(sub(pos, scl(f, cfg.chase.back_m)), [0, 0, cfg.chase.up_m]);
    const target = add(pos, scl(f, 1.5));
    const fw = norm(sub(target, eye));
    const rt = norm(cross(fw, [0, 0, 1]));
    const up = cross(rt, fw);
    const F = (H / 2) / Math.tan((cfg.chase.fov_deg * Math.PI / 180) / 2);
    return { eye, fw, rt, up, F, cx: W / 2, cy: H / 2 };
  }
  const toCam = (cam, p) => { const d = sub(p, cam.eye); return [dot(d, cam.rt), dot(d, cam.up), dot(d, cam.fw)]; };
  const project = (cam, c) => [cam.cx + cam.F * c[0] / c[2], cam.cy - cam.F * c[1] / c[2]];

  function clipNear(poly) {          // Sutherland-Hodgman against z >= NEAR (camera coordinates)
    const out = [];
    for (let i = 0; i < poly.length; i += 1) {
      const a = poly[i], b = poly[(i + 1) % poly.length];
      const ina = a[2] >= NEAR, inb = b[2] >= NEAR;
      if (ina) out.push(a);
      if (ina !== inb) {
        const t = (NEAR - a[2]) / (b[2] - a[2]);
        out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), NEAR]);
      }
    }
    return out;
  }
  function drawPoly(cam, worldPts, fill, stroke, lineWidth) {
    const c = clipNear(worldPts.map((p) => toCam(cam, p)));
    if (c.length < 3) return;
    ctx.beginPath();
    c.forEach((p, i) => { const s = project(cam, p); if (i) ctx.lineTo(s[0], s[1]); else ctx.moveTo(s[0], s[1]); });
    ctx.closePath();
    if (fill) { ctx.fillStyle = fill; ctx.fill(); }
    if (stroke) { ctx.strokeStyle = stroke; ctx.lineWidth = lineWidth || 1; ctx.stroke(); }
  }
  function drawLine(cam, a, b, stroke, lineWidth) {
    let ca = toCam(cam, a), cb = toCam(cam, b);
    if (ca[2] < NEAR && cb[2] < NEAR) return;
    if (ca[2] < NEAR || cb[2] < NEAR) {
      const t = (NEAR - ca[2]) / (cb[2] - ca[2]);
      const m = [ca[0] + t * (cb[0] - ca[0]), ca[1] + t * (cb[1] - ca[1]), NEAR];
      if (ca[2] < NEAR) ca = m; else cb = m;
    }
    const sa = project(cam, ca), sb = project(cam, cb);
    ctx.beginPath(); ctx.moveTo(sa[0], sa[1]); ctx.lineTo(sb[0], sb[1]);
    ctx.strokeStyle = stroke; ctx.lineWidth = lineWidth || 1; ctx.stroke();
  }

  const LIGHT = norm([0.4, 0.3, 1.0]);
  const rgb = (c, k) => `rgb(${Math.round(255 * Math.min(1, c[0] * k))},${Math.round(255 * Math.min(1, c[1] * k))},${Math.round(255 * Math.min(1, c[2] * k))})`;

  // faces of a box (centre, quaternion, size): [corners, outward normal]
  function boxFaces(p, q, s) {
    const h = [s[0] / 2, s[1] / 2, s[2] / 2];
    const corner = (i, j, k) => add(p, rotate(q, [i * h[0], j * h[1], k * h[2]]));
    const faces = [
      [[[1, -1, -1], [1, 1, -1], [1, 1, 1], [1, -1, 1]], [1, 0, 0]],
      [[[-1, 1, -1], [-1, -1, -1], [-1, -1, 1], [-1, 1, 1]], [-1, 0, 0]],
      [[[1, 1, -1], [-1, 1, -1], [-1, 1, 1], [1, 1, 1]], [0, 1, 0]],
      [[[-1, -1, -1], [1, -1, -1], [1, -1, 1], [-1, -1, 1]], [0, -1, 0]],
      [[[-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], [0, 0, 1]],
      [[[-1, 1, -1], [1, 1, -1], [1, -1, -1], [-1, -1, -1]], [0, 0, -1]],
    ];
    return faces.map(([cs, n]) => [cs.map((c) => corner(c[0], c[1], c[2])), rotate(q, n)]);
  }

  // ------------------------------------------------------------------ render
  function currentPose() {
    if (!state || !state.pose) return null;
    const { p, q, v } = state.pose;
    const dt = Math.min(0.1, (performance.now() - stateAt) / 1000);   // extrapolate between updates
    const vw = rotate(q, v);
    return { p: add(p, scl(vw, dt)), q: q, v: v };
  }

  function render() {
    const W = view.width, H = view.height;
    const sky = ctx.createLinearGradient(0, 0, 0, H);
    sky.addColorStop(0, '#6f95c0'); sky.addColorStop(1, '#c9d8e6');
    ctx.fillStyle = sky; ctx.fillRect(0, 0, W, H);
    const pose = currentPose();
    const pos = pose ? pose.p : [0, 0, 3];
    const yaw = pose ? yawOf(pose.q) : 0;
    const cam = makeCamera(pos, yaw, W, H);

    // floor and a 1 m grid
    drawPoly(cam, [[-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0]], '#7d8a6e');
    const gx0 = Math.floor(pos[0]) - 25, gy0 = Math.floor(pos[1]) - 25;
    for (let i = 0; i <= 50; i += 1) {
      const major = (gx0 + i) % 5 === 0;
      drawLine(cam, [gx0 + i, gy0, 0.001], [gx0 + i, gy0 + 50, 0.001], major ? '#5d6a50' : '#6e7b60', major ? 1.5 : 1);
      drawLine(cam, [gx0, gy0 + i, 0.001], [gx0 + 50, gy0 + i, 0.001], (gy0 + i) % 5 === 0 ? '#5d6a50' : '#6e7b60', 1);
    }

    // drawables sorted far to near (painter's algorithm)
    const items = [];
    const ground = pose ? surfaceBelow(pos[0], pos[1]) : 0;
    let shadowOn = pose && ground === 0 ? 'floor' : null;
    const goalCue = stats.cues && stats.cues.goal && stats.cues.goal.p ? stats.cues.goal : null;
    const goalBox = goalCue && goalCue.pad !== null ? scene.platforms.find((b) => b.id === goalCue.pad) : null;
    let goalDrawn = null;
    for (const b of scene.platforms) {
      const isGoal = cfg.show_goal && scene.goal === b.id;
      const isCue = goalBox === b;
      for (const [pts, n] of boxFaces(b.p, b.q, b.s)) {
        const centre = scl(pts.reduce(add, [0, 0, 0]), 0.25);
        if (dot(n, sub(cam.eye, centre)) <= 0) continue;
        const k = 0.55 + 0.45 * Math.max(0, dot(n, LIGHT));
        const top = n[2] > 0.9;
        const shadowHere = pose && top && Math.abs(ground - (b.p[2] + b.s[2] / 2)) < 1e-6 && !shadowOn;
        if (shadowHere) shadowOn = b.id;
        items.push({ depth: toCam(cam, centre)[2], draw: () => {
          drawPoly(cam, pts, rgb(b.c, k), isGoal ? '#ff2a1a' : 'rgba(0,0,0,0.35)', isGoal ? (top ? 4 : 2) : 1);
          if (isGoal) drawPoly(cam, pts, top ? 'rgba(255,40,20,0.55)' : 'rgba(255,40,20,0.25)');
          if (isCue && top) drawCue(cam, pts, goalCue.state);
          if (shadowHere) drawShadow(cam, pos, ground);
        } });
      }
    }
    if (goalBox) goalDrawn = screenOf(cam, goalCue.p);
    else if (goalCue) {               // no pad box for it (no scene): a ring where the estimate lies
      const ring = circle(goalCue.p, RING_M, 24);
      items.push({ depth: toCam(cam, goalCue.p)[2], draw: () => drawCue(cam, ring, goalCue.state) });
      goalDrawn = screenOf(cam, goalCue.p);
    }
    stats.cueDrawn.goal = goalCue ? { pad: goalCue.pad, state: goalCue.state, view: goalDrawn } : null;
    if (pose && shadowOn === 'floor') drawShadow(cam, pos, 0);
    if (pose) {
      // the drone: body, front marker, four legs, rotor discs; a drop line to the surface below
      const q = pose.q;
      const body = boxFaces(pos, q, [0.30, 0.30, 0.08]);
      for (const [pts, n] of body) {
        const centre = scl(pts.reduce(add, [0, 0, 0]), 0.25);
        if (dot(n, sub(cam.eye, centre)) <= 0) continue;
        const k = 0.6 + 0.4 * Math.max(0, dot(n, LIGHT));
        items.push({ depth: toCam(cam, centre)[2] - 0.05, draw: () => drawPoly(cam, pts, rgb([1.0, 0.55, 0.1], k), '#202020', 1) });
      }
      const nose = add(pos, rotate(q, [0.2, 0, 0.0]));
      items.push({ depth: toCam(cam, nose)[2] - 0.1, draw: () => drawLine(cam, pos, nose, '#d01010', 4) });
      for (const [sx, sy] of [[1, 1], [1, -1], [-1, 1], [-1, -1]]) {
        const hip = add(pos, rotate(q, [0.15 * sx, 0.15 * sy, -0.04]));
        const foot = add(pos, rotate(q, [0.15 * sx, 0.15 * sy, -0.12]));
        const hub = add(pos, rotate(q, [0.19 * sx, 0.19 * sy, 0.05]));
        const disc = [];
        for (let i = 0; i < 10; i += 1) {
          const a = 2 * Math.PI * i / 10;
          disc.push(add(hub, rotate(q, [0.11 * Math.cos(a), 0.11 * Math.sin(a), 0])));
        }
        items.push({ depth: toCam(cam, hip)[2] - 0.05, draw: () => drawLine(cam, hip, foot, '#222', 2) });
        items.push({ depth: toCam(cam, hub)[2] - 0.06, draw: () => drawPoly(cam, disc, 'rgba(40,40,40,0.45)', '#111', 1) });
      }
      const drop = [pos[0], pos[1], ground];
      items.push({ depth: toCam(cam, scl(add(pos, drop), 0.5))[2], draw: () => {
        ctx.setLineDash([6, 6]); drawLine(cam, sub(pos, [0, 0, 0.12]), drop, 'rgba(255,255,255,0.7)', 1.5); ctx.setLineDash([]);
      } });
    }
    items.sort((a, b) => b.depth - a.depth);
    for (const it of items) it.draw();
    stats.cueDrawn.push = pose ? drawPush(cam, pos, pose.q) : null;

    // labels: pad numbers, GOAL on the goal pad (always on top)
    ctx.font = 'bold 16px sans-serif'; ctx.textAlign = 'center';
    for (const b of scene.platforms) {
      const topC = toCam(cam, [b.p[0], b.p[1], b.p[2] + b.s[2] / 2 + 0.25]);
      if (topC[2] < NEAR) continue;
      const s = project(cam, topC);
      const isGoal = cfg.show_goal && scene.goal === b.id;
      ctx.fillStyle = isGoal ? '#ff2a1a' : 'rgba(255,255,255,0.9)';
      ctx.fillText(isGoal ? `${b.id + 1} GOAL` : String(b.id + 1), s[0], s[1]);
    }
    if (!pose) {
      ctx.fillStyle = 'rgba(0,0,0,0.6)'; ctx.fillRect(W / 2 - 160, H / 2 - 24, 320, 48);
      ctx.fillStyle = '#fff'; ctx.fillText('waiting for the vehicle (/odom)', W / 2, H / 2 + 6);
    }
  }
  function screenOf(cam, p) {
    const c = toCam(cam, p);
    return c[2] < NEAR ? null : project(cam, c).map((x) => Math.round(x));
  }
  function circle(p, r, n) {
    const pts = [];
    for (let i = 0; i < n; i += 1) {
      const a = 2 * Math.PI * i / n;
      pts.push([p[0] + r * Math.cos(a), p[1] + r * Math.sin(a), p[2] + 0.003]);
    }
    return pts;
  }
  // the goal cue on a world polygon (a pad's top face, or a ring): fill and outline by its state
  function drawCue(cam, pts, state) {
    const st = CUE_STYLE[state] || CUE_STYLE.unknown;
    ctx.setLineDash(st.dash);
    drawPoly(cam, pts, st.fill, st.stroke, st.width);
    ctx.setLineDash([]);
  }
  // the assistant's push (V - u, body FLU) as an arrow from the drone; returns its screen ends or null
  function drawPush(cam, pos, q) {
    const push = stats.cues && stats.cues.push;
    if (!push || Math.hypot(push[0], push[1], push[2]) < PUSH_MIN_MPS) return null;
    const tip = add(pos, scl(rotate(q, push), PUSH_M_PER_MPS));
    const a = toCam(cam, pos), b = toCam(cam, tip);
    if (a[2] < NEAR || b[2] < NEAR) return null;
    const sa = project(cam, a), sb = project(cam, b);
    const len = Math.hypot(sb[0] - sa[0], sb[1] - sa[1]);
    ctx.strokeStyle = PUSH_COLOUR; ctx.fillStyle = PUSH_COLOUR; ctx.lineWidth = 5; ctx.lineCap = 'round';
    ctx.beginPath(); ctx.moveTo(sa[0], sa[1]); ctx.lineTo(sb[0], sb[1]); ctx.stroke();
    if (len > 4) {                  // arrowhead in screen space
      const ux = (sb[0] - sa[0]) / len, uy = (sb[1] - sa[1]) / len, h = Math.min(18, 0.5 * len + 6);
      ctx.beginPath(); ctx.moveTo(sb[0] + ux * 4, sb[1] + uy * 4);
      ctx.lineTo(sb[0] - ux * h - uy * h * 0.6, sb[1] - uy * h + ux * h * 0.6);
      ctx.lineTo(sb[0] - ux * h + uy * h * 0.6, sb[1] - uy * h - ux * h * 0.6);
      ctx.closePath(); ctx.fill();
    }
    ctx.lineCap = 'butt';
    return { from: sa.map((x) => Math.round(x)), to: sb.map((x) => Math.round(x)) };
  }

  // ------------------------------------------------------------------ camera inset
  // world point -> the downward camera's optical frame (x right = body -y, y down the image = body -x, z = body -z)
  const cameraGeom = () => cfg.camera_geom || { vfov_deg: 58, offset_m: 0.05 };
  function toOptical(pose, p) {
    const q = pose.q;
    const d = rotate([-q[0], -q[1], -q[2], q[3]], sub(p, pose.p));
    const b = [d[0], d[1], d[2] + cameraGeom().offset_m];      // the optical centre lies offset_m below base_link
    return [-b[1], -b[0], -b[2]];
  }
  function insetPixel(o, w, h) {     // optical point -> inset canvas pixel (the image stretched over the inset)
    const f = (h / 2) / Math.tan(cameraGeom().vfov_deg * Math.PI / 360);
    return [(w / 2 + f * o[0] / o[2]) * inset.width / w, (h / 2 + f * o[1] / o[2]) * inset.height / h];
  }
  function drawInset(pose) {
    ictx.imageSmoothingEnabled = false;
    if (camBuf.width > 0 && stats.cameraFrames > 0) ictx.drawImage(camBuf, 0, 0, inset.width, inset.height);
    else { ictx.fillStyle = '#000'; ictx.fillRect(0, 0, inset.width, inset.height); }
    const cue = stats.cues && stats.cues.goal && stats.cues.goal.p ? stats.cues.goal : null;
    let drawn = null;
    if (cue && pose) {
      const w = stats.cameraFrames > 0 ? camBuf.width : 64, h = stats.cameraFrames > 0 ? camBuf.height : 64;
      const box = cue.pad !== null ? scene.platforms.find((b) => b.id === cue.pad) : null;
      const outline = box ? boxFaces(box.p, box.q, box.s)[4][0] : circle(cue.p, RING_M, 24);    // [4]: the top face
      const opt = outline.map((p) => toOptical(pose, p));
      const centre = toOptical(pose, cue.p);
      if (centre[2] > NEAR && opt.every((o) => o[2] > NEAR)) {
        const st = CUE_STYLE[cue.state] || CUE_STYLE.unknown;
        ictx.beginPath();
        opt.forEach((o, i) => { const s = insetPixel(o, w, h); if (i) ictx.lineTo(s[0], s[1]); else ictx.moveTo(s[0], s[1]); });
        ictx.closePath();
        if (st.fill) { ictx.fillStyle = st.fill; ictx.fill(); }
        ictx.setLineDash(st.dash.map((x) => x / 2)); ictx.strokeStyle = st.stroke; ictx.lineWidth = 2; ictx.stroke();
        ictx.setLineDash([]);
        const c = insetPixel(centre, w, h);
        ictx.beginPath(); ictx.moveTo(c[0] - 6, c[1]); ictx.lineTo(c[0] + 6, c[1]); ictx.moveTo(c[0], c[1] - 6); ictx.lineTo(c[0], c[1] + 6);
        ictx.strokeStyle = st.stroke; ictx.lineWidth = 2; ictx.stroke();
        if (c[0] >= 0 && c[0] <= inset.width && c[1] >= 0 && c[1] <= inset.height) drawn = c.map((x) => Math.round(x));
      }
    }
    if (stats.cueDrawn.goal) stats.cueDrawn.goal.inset = drawn;
  }

  function drawShadow(cam, pos, h) {
    const pts = [];
    for (let i = 0; i < 16; i += 1) {
      const a = 2 * Math.PI * i / 16;
      pts.push([pos[0] + 0.25 * Math.cos(a), pos[1] + 0.25 * Math.sin(a), h + 0.003]);
    }
    drawPoly(cam, pts, 'rgba(0,0,0,0.45)');
  }

  function resize() {
    const w = Math.max(MIN_W, Math.round(view.clientWidth)), h = Math.max(MIN_H, Math.round(view.clientHeight));
    if (view.width !== w || view.height !== h) { view.width = w; view.height = h; }
    stats.canvas = [view.width, view.height];
  }

  let fpsT0 = performance.now(), fpsN = 0;
  function frame(now) {
    resize();
    const t0 = performance.now();
    try { render(); if (cfg.camera) drawInset(currentPose()); } catch (err) { stats.errors += 1; console.error(err); }
    stats.renderMsTotal = (stats.renderMsTotal || 0) + (performance.now() - t0);   // draw time, for benches
    stats.frames += 1; fpsN += 1;
    if (now - fpsT0 >= 1000) {
      stats.fps = fpsN * 1000 / (now - fpsT0); fpsN = 0; fpsT0 = now;
      el('fps').textContent = stats.fps.toFixed(0) + ' fps';
    }
    requestAnimationFrame(frame);
  }
  connect();
  view.focus();
  requestAnimationFrame(frame);
})();
