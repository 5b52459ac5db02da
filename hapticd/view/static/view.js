// hapticd view: the scene drawn on a canvas from the daemon's telemetry, and the
// experimenter's panels. Messages arrive over one WebSocket at the telemetry rate;
// drawing runs on requestAnimationFrame at the display's rate whatever the loop's.
// Units as in the daemon: positions m, forces N; shown in mm and N.
"use strict";
(() => {
  const query = new URLSearchParams(location.search);
  const key = query.get("key") || "";
  const subject = query.get("mode") === "subject";
  document.body.className = subject ? "subject" : "experimenter";
  document.title = subject ? "hapticd" : "hapticd view";
  const $ = (id) => document.getElementById(id);

  const TRACE_S = 10; // s of force traces
  const FINGER_COLOURS = ["#4a6fa5", "#59a14f", "#b07aa1", "#9c755f", "#76b7b2"];
  const CONTACT = "#f28e2b";
  const FULL = "#d62728";
  const RENDERED = "#1f9e89";
  const ARROW_SCALES = [0.02, 0.01, 0.005, 0.002, 0.001]; // m of arrow per N
  const ARROW_MAX_M = 0.08;

  const state = {
    sample: null, // the latest telemetry
    status: null, // the latest status (the subject's: geometry only)
    link: null,
    traces: [], // {t, full: [N per finger], rend: [N per finger]}
    frames: 0,
    params: null,
    target: null, // the camera looks here: the object's first position
    reference: null, // z of the reference plane when the scene has no ground
  };
  // The subject's view is closer: the scene alone, large.
  const DEFAULT_CAM = { az: -2.05, el: 0.42, dist: subject ? 0.24 : 0.3 };
  const cam = { ...DEFAULT_CAM };

  // -- the stream: one WebSocket, the view's messages in, the page's commands out ---------

  const mode = subject ? "subject" : "experimenter";
  let ws = null;
  let viewLost = false; // the WebSocket closed: the view stopped, or restarts
  let noteTimer = null;
  let nextRef = 1;
  const pending = new Map(); // ref -> the callback of a command awaiting its reply

  function connect() {
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const sock = new WebSocket(`${scheme}//${location.host}/ws?key=${encodeURIComponent(key)}&mode=${mode}`);
    ws = sock;
    sock.onopen = () => {
      if (viewLost) {
        viewLost = false;
        note(subject ? null : "reconnected to hapticd view");
      }
      if (noteTimer === null) onLink(state.link);
    };
    sock.onmessage = (e) => {
      const m = JSON.parse(e.data);
      if (m.type === "hello") onHello(m.data);
      else if (m.type === "telemetry") onTelemetry(m.data);
      else if (m.type === "status") onStatus(m.data);
      else if (m.type === "link") onLink(m.data);
      else if (m.type === "event") onEvent(m.data);
      else if (m.type === "reply") {
        const done = pending.get(m.ref);
        pending.delete(m.ref);
        if (done) done(m);
      }
    };
    sock.onclose = () => {
      if (ws !== sock) return;
      viewLost = true;
      for (const done of pending.values()) {
        done({ ok: false, error: { code: "no_view", message: "the view went away" } });
      }
      pending.clear();
      whyClosed();
      setTimeout(connect, 1000);
    };
  }

  // Whose page this is, as the view says from the key: a subject's URL without
  // mode=subject still gets only the subject's data; it is drawn as the subject's page.
  function onHello(hello) {
    if (hello && hello.role === "subject" && !subject) {
      const q = new URLSearchParams(location.search);
      q.set("mode", "subject");
      location.replace(`${location.pathname}?${q}`);
    }
  }

  // The WebSocket API does not say why a connection failed: ask the view over HTTP.
  async function whyClosed() {
    let text = "cannot reach hapticd view (stopped?); reconnecting";
    try {
      const r = await fetch(`/api/status?key=${encodeURIComponent(key)}`);
      if (r.status === 403) text = "hapticd view does not know this page's key: open the URL it printed";
      else if (r.ok) text = "lost hapticd view; reconnecting";
    } catch (err) {
      // nothing answers at the view's address: the text above
    }
    if (viewLost) banner(subject ? "waiting" : text);
  }

  // Send a command; ``done`` gets its reply (``{ok, result}`` or ``{ok: false, error}``).
  function send(msg, done) {
    if (!ws || ws.readyState !== WebSocket.OPEN) {
      done({ ok: false, error: { code: "no_view", message: "not connected to hapticd view" } });
      return;
    }
    const ref = nextRef++;
    pending.set(ref, done);
    ws.send(JSON.stringify({ ...msg, ref }));
  }

  // A short note in the banner (a reconnection), cleared after a few seconds.
  function note(text) {
    clearTimeout(noteTimer);
    noteTimer = null;
    if (text !== null) {
      banner(text);
      noteTimer = setTimeout(() => {
        noteTimer = null;
        onLink(state.link);
      }, 3000);
    }
  }

  function norm(v) {
    return Math.hypot(v[0], v[1], v[2]);
  }

  function onTelemetry(s) {
    const prev = state.sample;
    state.sample = s;
    if (state.target === null || (prev && s.tick < prev.tick)) {
      state.target = s.object_pos.slice(); // a restarted daemon: look again
      state.traces = [];
      state.reference = null;
    }
    $("tick").textContent = String(s.tick);
    if (subject) return;
    $("t").textContent = `${s.t.toFixed(3)} s`;
    $("overruns").textContent = String(s.overruns);
    $("residuals").textContent =
      `internal ${s.residual_internal.toFixed(3)} N, external ${s.residual_external.toFixed(3)} N`;
    state.traces.push({
      t: s.t,
      full: s.contact_force.map(norm),
      rend: s.rendered_force.map(norm),
    });
    while (state.traces.length && state.traces[0].t < s.t - TRACE_S) state.traces.shift();
  }

  function onLink(link) {
    state.link = link;
    if (viewLost) return; // the view's own banner stands
    if (link && !link.connected) banner(subject ? "waiting" : `no daemon: ${link.message}`);
    else if (noteTimer === null) banner(null);
    if (!link) return;
    if (subject) return;
    const el = $("link");
    el.textContent = link.connected ? `connected (${link.socket})` : `not connected: ${link.message}`;
    el.className = link.connected ? "good" : "bad";
  }

  function banner(text) {
    const b = $("banner");
    b.hidden = text === null;
    if (text !== null) b.textContent = text;
  }

  const fmt = (v, digits = 3) => (v === null || v === undefined ? "n/a" : Number(v).toPrecision(digits));
  // Microseconds: two decimals below 10 us, whole numbers above 100 us.
  const us = (v) => {
    if (v === null || v === undefined) return "n/a";
    return `${v < 10 ? v.toFixed(2) : v < 100 ? v.toFixed(1) : Math.round(v)} us`;
  };

  function onStatus(st) {
    state.status = st;
    onPrompt(st.prompt || null);
    onScreen(st.screen || null);
    if (subject) return;
    const v = st.view || {};
    const achieved = v.achieved_hz === null || v.achieved_hz === undefined
      ? "" : `, achieved ${v.achieved_hz.toFixed(0)} Hz`;
    $("rate").textContent = `${st.rate_hz} Hz target${achieved}${st.paced ? "" : " (unpaced)"}`;
    const pe = st.period_error_us || {};
    $("perr").textContent = `p50 ${us(pe.p50)}, p99 ${us(pe.p99)}, max ${us(pe.max)}`;
    $("overruns").textContent = String(st.overruns);
    const fault = $("fault");
    fault.textContent = st.fault ? `LATCHED at tick ${st.fault.tick}: ${st.fault.cause}` : "none";
    fault.className = st.fault ? "bad" : "good";
    $("devices").textContent = (st.devices || [])
      .map((d, i) => `${(st.fingers || [])[i] || d.serial}: ${d.connected ? "connected" : "LOST"}, limit ${d.force_limit_n} N`)
      .join("; ");
    $("allocator").textContent = st.allocator;
    $("stages").textContent = (st.stages || []).join(" ");
    const pa = st.passivity;
    $("passivity").textContent = !pa || !pa.enabled ? "off"
      : `energy ${pa.energy_j.map((e) => fmt(e)).join(", ")} J; damping ${pa.damping_n_s_per_m.map((b) => fmt(b)).join(", ")} N s/m`;
    const reloads = Array.isArray(st.reloads) ? st.reloads.length : 0;
    $("profile").textContent = `${st.profile}${reloads ? `, reloaded ${reloads} time(s)` : ""}`;
    const sc = st.scene || {};
    const size = sc.bounds_m
      ? sc.bounds_m[1].map((hi, i) => ((hi - sc.bounds_m[0][i]) * 1e3).toFixed(0)).join(" x ") + " mm"
      : "";
    $("object").textContent = `${sc.shape}, ${sc.fixed ? "fixed" : "free"}, ${size}`;
    $("stiffness").textContent = `${sc.stiffness_n_per_m} N/m`;
    $("damping").textContent = `${sc.damping_n_s_per_m} N s/m`;
    $("friction").textContent = sc.friction ? `static ${sc.friction[0]}, dynamic ${sc.friction[1]}` : "-";
    $("mass").textContent = `${sc.mass_kg} kg`;
    const rec = st.recording;
    const r = $("recording");
    r.textContent = !rec ? "off"
      : `${rec.path}: ${rec.ticks} ticks, ${rec.written} written, ${rec.dropped} dropped` +
        (rec.error ? `; ERROR ${rec.error}` : "");
    r.className = rec && (rec.error || rec.dropped) ? "bad" : "";
    onVirtual(st, !!v.control);
    $("control").hidden = !v.control;
    $("readonly").hidden = !!v.control;
    if (v.control && state.params === null) loadParams();
  }

  // -- changes (--control) ---------------------------------------------------------------

  async function loadParams() {
    state.params = [];
    const reply = await fetch(`/api/params?key=${encodeURIComponent(key)}`);
    const body = await reply.json();
    state.params = body.params;
    const sel = $("set-param");
    sel.replaceChildren(...body.params.map((p) => {
      const o = document.createElement("option");
      o.value = p.name;
      o.textContent = p.alias || p.name;
      return o;
    }));
    const hint = () => {
      const p = state.params.find((q) => q.name === sel.value);
      $("set-syntax").textContent = p
        ? `${p.name}: ${p.choices.length ? p.choices.join(", ") : p.syntax}, ${p.range}` : "";
    };
    sel.onchange = hint;
    hint();
  }

  $("set-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const out = $("set-result");
    const param = $("set-param").value;
    const value = $("set-value").value.trim();
    send({ type: "set", param, value }, (r) => {
      out.className = r.ok ? "good" : "bad";
      out.textContent = r.ok
        ? `${param} = ${value}: applied at tick ${r.result.applied_at_tick}`
        : `${r.error.code}: ${r.error.message}`;
    });
  });

  // -- virtual devices (backend virtual): moved from here, with --control ------------------

  // The fingers whose device is virtual, from the status; where each is sent (world, m).
  let virtualFingers = [];
  const targets = new Map(); // finger -> [x, y, z] m, the last target the daemon took
  const moving = new Map(); // finger -> a target waiting for the reply to the last move
  const inFlight = new Set(); // fingers with a move awaiting its reply
  let lastView = null; // the camera of the last frame drawn (for picking and dragging)

  function onVirtual(st, control) {
    virtualFingers = control
      ? (st.devices || []).map((d, i) => (d.model === "virtual" ? i : -1)).filter((i) => i >= 0)
      : [];
    $("virtual").hidden = virtualFingers.length === 0;
  }

  let shownSample = null;
  function showVirtual() {
    const s = state.sample;
    if (!s || s === shownSample || virtualFingers.length === 0) return;
    shownSample = s;
    const names = (state.status && state.status.fingers) || [];
    const rows = [];
    for (const i of virtualFingers) {
      const dt = document.createElement("dt");
      dt.textContent = names[i] || `finger ${i}`;
      const dd = document.createElement("dd");
      const p = s.device_pos[i].map((c) => (c * 1e3).toFixed(1)).join(", ");
      const f = norm(s.rendered_force[i]);
      dd.dataset.testid = `virtual-${i}`;
      dd.dataset.force = String(f);
      dd.textContent = `(${p}) mm, ${s.in_contact[i] ? "touching" : "free"}, rendered ${f.toFixed(2)} N`;
      rows.push(dt, dd);
    }
    $("virtual-list").replaceChildren(...rows);
  }

  function targetOf(i) {
    if (targets.has(i)) return targets.get(i).slice();
    return state.sample ? state.sample.device_pos[i].slice() : [0, 0, 0];
  }

  // Send finger i towards p (world, m): one move in flight per finger, the latest kept.
  function moveTo(i, p) {
    targets.set(i, p.slice());
    if (inFlight.has(i)) {
      moving.set(i, p);
      return;
    }
    inFlight.add(i);
    send({ type: "move", finger: i, position_m: p }, (r) => {
      inFlight.delete(i);
      const out = $("virtual-result");
      if (r.ok) {
        out.textContent = "";
        if (!moving.has(i)) targets.set(i, r.result.target_m);
      } else {
        out.textContent = `${r.error.code}: ${r.error.message}`;
        out.className = "bad";
      }
      if (moving.has(i)) {
        const next = moving.get(i);
        moving.delete(i);
        moveTo(i, next);
      }
    });
  }

  // The virtual finger drawn under the pointer (canvas pixels), or -1.
  function pickFinger(x, y) {
    const s = state.sample;
    if (!s || !lastView || virtualFingers.length === 0) return -1;
    const radii = (state.status.scene && state.status.scene.finger_radii_m) || [];
    let best = -1;
    let bestD = Infinity;
    for (const i of virtualFingers) {
      for (const p of [s.device_pos[i], s.proxy_pos[i]]) {
        const q = lastView.project(p);
        if (!q) continue;
        const d = Math.hypot(q.x - x, q.y - y);
        const reach = lastView.px(radii[i] || 0.008, q.z) + 8 * (window.devicePixelRatio || 1);
        if (d <= reach && d < bestD) {
          best = i;
          bestD = d;
        }
      }
    }
    return best;
  }

  const STEP_M = 0.002;
  document.addEventListener("keydown", (e) => {
    if (subject || virtualFingers.length === 0 || e.ctrlKey || e.altKey || e.metaKey) return;
    if (e.target && ["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName)) return;
    const step = e.shiftKey ? 2.5 * STEP_M : STEP_M;
    const key = e.key.toLowerCase();
    const now = virtualFingers.map((i) => targetOf(i));
    let move = null;
    if (key === "arrowup" || key === "arrowdown") {
      const dz = key === "arrowup" ? step : -step;
      move = now.map((p) => [p[0], p[1], p[2] + dz]);
    } else if (key === "s" || key === "r") {
      // Towards (squeeze) or away from (release) the fingers' middle, horizontally; one
      // finger alone: towards the object.
      const mid = now.length > 1
        ? scale(now.reduce((a, p) => add(a, p), [0, 0, 0]), 1 / now.length)
        : state.sample.object_pos;
      move = now.map((p) => {
        const d = unit([mid[0] - p[0], mid[1] - p[1], 0]);
        return add(p, scale(d, key === "s" ? step : -step));
      });
    }
    if (move === null) return;
    e.preventDefault();
    virtualFingers.forEach((i, k) => moveTo(i, move[k]));
  });

  // -- the prompt: the subject's answer buttons, the experimenter's panel -------------------

  let promptShown = null; // the id of the prompt the buttons are for
  const keys = new Map(); // key -> choice, while a prompt is shown

  // Keys for the choices: each one's first letter where no other choice shares it, and
  // 1..n always.
  function keysFor(choices) {
    const out = new Map();
    const first = choices.map((c) => c[0]);
    choices.forEach((c, i) => {
      out.set(String(i + 1), c);
      if (first.filter((f) => f === c[0]).length === 1) out.set(c[0], c);
    });
    return out;
  }

  function onPrompt(p) {
    const box = $("prompt");
    if (!subject) {
      $("prompt-state").textContent = p
        ? `${p.id}: "${p.question}" (${p.choices.join(" / ")}), waiting for the answer`
        : "none";
      return;
    }
    if (p === null) {
      box.hidden = true;
      promptShown = null;
      keys.clear();
      return;
    }
    if (promptShown === p.id) return;
    promptShown = p.id;
    keys.clear();
    for (const [k, c] of keysFor(p.choices)) keys.set(k, c);
    $("prompt-question").textContent = p.question;
    $("prompt-result").textContent = "";
    $("prompt-choices").replaceChildren(...p.choices.map((c, i) => {
      const b = document.createElement("button");
      b.type = "button";
      b.className = "answer";
      b.dataset.testid = `answer-${c}`;
      b.dataset.choice = c;
      const hint = [...keys].filter(([, v]) => v === c).map(([k]) => k).reverse().join(" or ");
      const label = document.createElement("span");
      label.textContent = c;
      const small = document.createElement("small");
      small.textContent = `key ${hint}`;
      b.append(label, small);
      b.onclick = () => answer(p.id, c);
      return b;
    }));
    box.hidden = false;
  }

  function answer(id, choice) {
    if (promptShown !== id) return;
    const buttons = [...document.querySelectorAll("#prompt-choices button")];
    buttons.forEach((b) => { b.disabled = true; });
    const out = $("prompt-result");
    send({ type: "respond", prompt: id, choice }, (r) => {
      if (r.ok) {
        out.textContent = `answered: ${choice}`;
        out.className = "good";
      } else {
        out.textContent = `not recorded: ${r.error.message}`;
        out.className = "bad";
        buttons.forEach((b) => { b.disabled = false; });
      }
    });
  }

  document.addEventListener("keydown", (e) => {
    if (!subject || promptShown === null || e.ctrlKey || e.altKey || e.metaKey) return;
    const choice = keys.get(e.key.toLowerCase());
    if (choice !== undefined) {
      e.preventDefault();
      answer(promptShown, choice);
    }
  });

  // -- the subject's screen: text states the runner sets (never anything of the condition) --

  function onScreen(sc) {
    if (!subject) {
      $("screen-state").textContent = sc
        ? `${sc.state}${sc.practice ? " (practice)" : ""}${sc.text ? `: ${sc.text.slice(0, 60)}` : ""}`
        : "none";
      return;
    }
    const box = $("screen");
    box.hidden = sc === null;
    if (sc === null) return;
    const shown = sc.state + (sc.practice ? ":practice" : "");
    if (box.dataset.shown !== shown) {
      // The states shown, the last 60 (for scripts and tests: a state may last 0.1 s).
      box.dataset.seen = [...(box.dataset.seen || "").split(" ").filter(Boolean), shown]
        .slice(-60).join(" ");
    }
    box.dataset.shown = shown;
    box.dataset.state = sc.state;
    box.classList.toggle("correct", sc.correct === true);
    box.classList.toggle("incorrect", sc.correct === false);
    $("screen-practice").hidden = !sc.practice;
    $("screen-text").textContent = sc.text || "";
    const secs = $("screen-seconds");
    secs.hidden = sc.seconds === null || sc.seconds === undefined;
    if (!secs.hidden) secs.textContent = `${Math.ceil(sc.seconds)} s`;
    const prog = $("screen-progress");
    prog.hidden = !Array.isArray(sc.progress);
    if (!prog.hidden) prog.textContent = `trial ${sc.progress[0]} of ${sc.progress[1]}`;
  }

  // Whether the experiment hides the scene from the subject (the view then sends no
  // geometry or motion either).
  function sceneHidden() {
    const sc = state.status && state.status.screen;
    return subject && !!sc && sc.scene === false;
  }

  // The daemon's events: the experimenter's page shows the last answer.
  function onEvent(ev) {
    if (subject) return;
    if (ev.event === "response") {
      $("prompt-last").textContent = `${ev.prompt}: ${ev.choice} (tick ${ev.tick})`;
    }
  }

  // -- the camera and projection ------------------------------------------------------------

  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
  function scale(a, k) { return [a[0] * k, a[1] * k, a[2] * k]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function cross(a, b) {
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  }
  function unit(a) { const n = norm(a) || 1; return scale(a, 1 / n); }
  function rotate(R, v) { return [dot(R[0], v), dot(R[1], v), dot(R[2], v)]; }

  // A perspective camera orbiting the target: azimuth and elevation (rad), distance (m).
  function makeView(target, W, H) {
    const ce = Math.cos(cam.el);
    const eye = add(target, scale([ce * Math.cos(cam.az), ce * Math.sin(cam.az), Math.sin(cam.el)], cam.dist));
    const fwd = unit(sub(target, eye));
    const right = unit(cross(fwd, [0, 0, 1]));
    const up = cross(right, fwd);
    const focal = (0.5 * Math.min(W, H)) / Math.tan((35 * Math.PI) / 360);
    return {
      eye,
      right,
      up,
      focal,
      project(p) {
        const d = sub(p, eye);
        const z = dot(d, fwd);
        if (z < 0.01) return null; // behind the camera
        return { x: W / 2 + (focal * dot(d, right)) / z, y: H / 2 - (focal * dot(d, up)) / z, z };
      },
      px(radius, z) { return (focal * radius) / z; },
    };
  }

  // -- the scene ----------------------------------------------------------------------------

  const BOX_FACES = [
    { idx: [0, 2, 6, 4], n: [-1, 0, 0] }, { idx: [1, 3, 7, 5], n: [1, 0, 0] },
    { idx: [0, 1, 5, 4], n: [0, -1, 0] }, { idx: [2, 3, 7, 6], n: [0, 1, 0] },
    { idx: [0, 1, 3, 2], n: [0, 0, -1] }, { idx: [4, 5, 7, 6], n: [0, 0, 1] },
  ];

  function boxCorners(bounds, R, p) {
    const out = [];
    for (let i = 0; i < 8; i++) {
      const c = [bounds[i & 1 ? 1 : 0][0], bounds[i & 2 ? 1 : 0][1], bounds[i & 4 ? 1 : 0][2]];
      out.push(add(rotate(R, c), p));
    }
    return out;
  }

  function fit(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr));
    const h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w;
      canvas.height = h;
    }
    return dpr;
  }

  function polygon(ctx, pts) {
    if (pts.some((q) => q === null)) return false;
    ctx.beginPath();
    pts.forEach((q, i) => (i ? ctx.lineTo(q.x, q.y) : ctx.moveTo(q.x, q.y)));
    ctx.closePath();
    return true;
  }

  function segment(ctx, view, a, b) {
    const p = view.project(a);
    const q = view.project(b);
    if (!p || !q) return;
    ctx.beginPath();
    ctx.moveTo(p.x, p.y);
    ctx.lineTo(q.x, q.y);
    ctx.stroke();
  }

  // Convex hull (monotone chain) of 2-D points {x, y}: the box's shadow.
  function hull(points) {
    const p = points.slice().sort((a, b) => a.x - b.x || a.y - b.y);
    const turn = (o, a, b) => (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x);
    const lower = [];
    for (const q of p) {
      while (lower.length >= 2 && turn(lower[lower.length - 2], lower[lower.length - 1], q) <= 0) lower.pop();
      lower.push(q);
    }
    const upper = [];
    for (const q of p.reverse()) {
      while (upper.length >= 2 && turn(upper[upper.length - 2], upper[upper.length - 1], q) <= 0) upper.pop();
      upper.push(q);
    }
    return lower.slice(0, -1).concat(upper.slice(0, -1));
  }

  // The floor: the scene's ground, else a reference plane under the object's first pose.
  function floorOf(scene, corners) {
    const ground = (scene.surfaces || []).find((s) => s.normal[2] === 1 && s.normal[0] === 0 && s.normal[1] === 0);
    if (ground) return { z: ground.offset_m, real: true };
    if (state.reference === null) state.reference = Math.min(...corners.map((c) => c[2]));
    return { z: state.reference, real: false };
  }

  function extentOf(scene, target) {
    // Walls bound the floor where the scene has them; else 10 cm around the object.
    const ext = { x0: target[0] - 0.1, x1: target[0] + 0.1, y0: target[1] - 0.1, y1: target[1] + 0.1 };
    for (const s of scene.surfaces || []) {
      const [nx, ny, nz] = s.normal;
      if (nz !== 0) continue;
      if (Math.abs(nx) === 1 && ny === 0) {
        const x = s.offset_m / nx;
        if (nx < 0) ext.x1 = x; else ext.x0 = x;
      } else if (Math.abs(ny) === 1 && nx === 0) {
        const y = s.offset_m / ny;
        if (ny < 0) ext.y1 = y; else ext.y0 = y;
      }
    }
    return ext;
  }

  function drawFloor(ctx, view, floor, scene, target, dpr) {
    const ext = extentOf(scene, target);
    const z = floor.z;
    ctx.lineWidth = 1 * dpr;
    ctx.strokeStyle = subject ? "rgba(200,210,225,0.18)" : floor.real ? "rgba(60,70,90,0.28)" : "rgba(60,70,90,0.14)";
    const step = 0.01;
    for (let x = Math.ceil(ext.x0 / step) * step; x <= ext.x1 + 1e-9; x += step) {
      segment(ctx, view, [x, ext.y0, z], [x, ext.y1, z]);
    }
    for (let y = Math.ceil(ext.y0 / step) * step; y <= ext.y1 + 1e-9; y += step) {
      segment(ctx, view, [ext.x0, y, z], [ext.x1, y, z]);
    }
    // Walls: translucent panels 4 cm high where the scene has them.
    const h = 0.04;
    ctx.fillStyle = subject ? "rgba(200,210,225,0.08)" : "rgba(90,100,120,0.08)";
    ctx.strokeStyle = subject ? "rgba(200,210,225,0.3)" : "rgba(60,70,90,0.35)";
    for (const s of scene.surfaces || []) {
      const [nx, ny, nz] = s.normal;
      if (nz !== 0) continue;
      let a;
      let b;
      if (Math.abs(nx) === 1 && ny === 0) {
        const x = s.offset_m / nx;
        a = [x, ext.y0, z];
        b = [x, ext.y1, z];
      } else if (Math.abs(ny) === 1 && nx === 0) {
        const y = s.offset_m / ny;
        a = [ext.x0, y, z];
        b = [ext.x1, y, z];
      } else {
        continue; // a slanted wall: not drawn
      }
      const quad = [a, b, [b[0], b[1], z + h], [a[0], a[1], z + h]].map(view.project);
      if (polygon(ctx, quad)) { ctx.fill(); ctx.stroke(); }
    }
    if (!subject) {
      const label = view.project([ext.x1, ext.y0, z]);
      if (label) {
        ctx.fillStyle = "rgba(60,70,90,0.7)";
        ctx.font = `${11 * dpr}px system-ui, sans-serif`;
        ctx.fillText(floor.real ? "ground" : "reference plane (no ground)", label.x + 4 * dpr, label.y);
      }
    }
  }

  function arrow(ctx, view, from, force, colour, dash, dpr) {
    const len = norm(force) * arrowScale();
    if (len < 1e-4) return;
    const to = add(from, scale(force, arrowScale()));
    const p = view.project(from);
    const q = view.project(to);
    if (!p || !q) return;
    ctx.strokeStyle = colour;
    ctx.fillStyle = colour;
    ctx.lineWidth = 2.5 * dpr;
    ctx.setLineDash(dash ? [6 * dpr, 4 * dpr] : []);
    ctx.beginPath();
    ctx.moveTo(p.x, p.y);
    ctx.lineTo(q.x, q.y);
    ctx.stroke();
    ctx.setLineDash([]);
    const ang = Math.atan2(q.y - p.y, q.x - p.x);
    const hs = 9 * dpr;
    ctx.beginPath();
    ctx.moveTo(q.x, q.y);
    ctx.lineTo(q.x - hs * Math.cos(ang - 0.4), q.y - hs * Math.sin(ang - 0.4));
    ctx.lineTo(q.x - hs * Math.cos(ang + 0.4), q.y - hs * Math.sin(ang + 0.4));
    ctx.closePath();
    ctx.fill();
  }

  // Arrows: the largest force of the traces fits in ARROW_MAX_M; steps, not a sliding scale.
  let arrowM = ARROW_SCALES[0];
  function arrowScale() { return arrowM; }
  function chooseArrowScale() {
    let fmax = 0;
    for (const tr of state.traces) for (const f of tr.full.concat(tr.rend)) fmax = Math.max(fmax, f);
    arrowM = ARROW_SCALES.find((k) => k * fmax <= ARROW_MAX_M) || ARROW_SCALES[ARROW_SCALES.length - 1];
    $("arrow-scale").textContent = `arrows: 1 N = ${(arrowM * 1e3).toFixed(0)} mm`;
  }

  function sphere(ctx, q, rpx, colour, contact, dpr) {
    const g = ctx.createRadialGradient(q.x - rpx * 0.35, q.y - rpx * 0.35, rpx * 0.1, q.x, q.y, rpx);
    g.addColorStop(0, "#ffffff");
    g.addColorStop(0.35, contact ? CONTACT : colour);
    g.addColorStop(1, contact ? "#a3520b" : "#1f2f48");
    ctx.fillStyle = g;
    ctx.beginPath();
    ctx.arc(q.x, q.y, rpx, 0, 2 * Math.PI);
    ctx.fill();
    if (contact) {
      ctx.strokeStyle = CONTACT;
      ctx.lineWidth = 3 * dpr;
      ctx.beginPath();
      ctx.arc(q.x, q.y, rpx + 4 * dpr, 0, 2 * Math.PI);
      ctx.stroke();
    }
  }

  function drawScene() {
    const canvas = $("scene");
    const ctx = canvas.getContext("2d");
    const dpr = fit(canvas);
    const W = canvas.width;
    const H = canvas.height;
    ctx.fillStyle = subject ? "#20242c" : "#f4f5f7";
    ctx.fillRect(0, 0, W, H);
    canvas.dataset.scene = sceneHidden() ? "hidden" : "shown";
    if (sceneHidden()) return;
    const s = state.sample;
    const st = state.status;
    if (!s || !st || !st.scene || !st.scene.bounds_m) {
      ctx.fillStyle = subject ? "#aaa" : "#667085";
      ctx.font = `${14 * dpr}px system-ui, sans-serif`;
      ctx.textAlign = "center";
      ctx.fillText(subject ? "" : "waiting for telemetry", W / 2, H / 2);
      ctx.textAlign = "start";
      return;
    }
    const scene = st.scene;
    const view = makeView(state.target || s.object_pos, W, H);
    const corners = boxCorners(scene.bounds_m, s.object_rot, s.object_pos);
    const floor = floorOf(scene, corners);
    drawFloor(ctx, view, floor, scene, state.target || s.object_pos, dpr);
    const radii = scene.finger_radii_m || [];
    const nf = s.proxy_pos.length;

    // Shadows on the floor (straight down): the object's outline, each fingertip.
    ctx.fillStyle = subject ? "rgba(0,0,0,0.35)" : "rgba(20,30,50,0.12)";
    const shadow = corners.map((c) => view.project([c[0], c[1], floor.z]));
    if (shadow.every((q) => q)) {
      const pts = hull(shadow);
      if (polygon(ctx, pts)) ctx.fill();
    }
    for (let i = 0; i < nf; i++) {
      const p = s.proxy_pos[i];
      if (p[2] < floor.z) continue;
      const q = view.project([p[0], p[1], floor.z]);
      if (!q) continue;
      const r = view.px(radii[i] || 0.008, q.z);
      ctx.beginPath();
      ctx.ellipse(q.x, q.y, r, r * 0.45, 0, 0, 2 * Math.PI);
      ctx.fill();
    }

    // A translucent box: faces turned away first, then the fingertips, then the near faces.
    const proj = corners.map(view.project);
    const faces = BOX_FACES.map((f) => {
      const centre = scale(f.idx.reduce((acc, i) => add(acc, corners[i]), [0, 0, 0]), 0.25);
      const n = rotate(s.object_rot, f.n);
      return { f, near: dot(n, sub(view.eye, centre)) > 0 };
    });
    const anyContact = s.in_contact.some((c) => c);
    const drawFaces = (near) => {
      for (const { f, near: isNear } of faces) {
        if (isNear !== near) continue;
        if (!polygon(ctx, f.idx.map((i) => proj[i]))) continue;
        ctx.fillStyle = subject ? "rgba(120,160,220,0.55)" : near ? "rgba(120,160,220,0.28)" : "rgba(120,160,220,0.40)";
        ctx.fill();
        ctx.strokeStyle = anyContact && !subject ? CONTACT : subject ? "#9db8e0" : "#2c4a78";
        ctx.lineWidth = (near ? 2 : 1) * dpr;
        ctx.stroke();
      }
    };
    drawFaces(false);

    // Fingertips, far first: the device (dashed outline) and the proxy (a sphere), the
    // penetration between them, and the forces from the proxy.
    const order = [...Array(nf).keys()].sort((a, b) => {
      const qa = view.project(s.proxy_pos[a]);
      const qb = view.project(s.proxy_pos[b]);
      return (qb ? qb.z : 0) - (qa ? qa.z : 0);
    });
    for (const i of order) {
      const r = radii[i] || 0.008;
      const colour = FINGER_COLOURS[i % FINGER_COLOURS.length];
      const contact = !!s.in_contact[i];
      const qp = view.project(s.proxy_pos[i]);
      if (!subject && s.device_pos) {
        const qd = view.project(s.device_pos[i]);
        if (qd) {
          ctx.strokeStyle = "#555";
          ctx.lineWidth = 1.5 * dpr;
          ctx.setLineDash([4 * dpr, 3 * dpr]);
          ctx.beginPath();
          ctx.arc(qd.x, qd.y, view.px(r, qd.z), 0, 2 * Math.PI);
          ctx.stroke();
          if (qp) {
            ctx.beginPath();
            ctx.moveTo(qd.x, qd.y);
            ctx.lineTo(qp.x, qp.y);
            ctx.stroke();
          }
          ctx.setLineDash([]);
        }
      }
      if (qp) sphere(ctx, qp, view.px(r, qp.z), colour, contact, dpr);
      if (!subject && s.contact_force) {
        arrow(ctx, view, s.proxy_pos[i], s.contact_force[i], FULL, false, dpr);
        arrow(ctx, view, s.proxy_pos[i], s.rendered_force[i], RENDERED, true, dpr);
      }
      if (!subject && qp) {
        ctx.fillStyle = "#1d2330";
        ctx.font = `${12 * dpr}px system-ui, sans-serif`;
        const name = (st.fingers || [])[i] || `finger ${i}`;
        ctx.fillText(name, qp.x + view.px(r, qp.z) + 6 * dpr, qp.y - view.px(r, qp.z));
      }
    }
    drawFaces(true);
    lastView = view;
    if (!subject && virtualFingers.length) {
      // Where the virtual fingertips and the object are drawn (CSS px): for scripts and tests.
      const css = (p) => {
        const q = view.project(p);
        return q ? [q.x / dpr, q.y / dpr] : null;
      };
      canvas.dataset.virtual = JSON.stringify({
        fingers: Object.fromEntries(virtualFingers.map((i) => [i, css(s.device_pos[i])])),
        object: css(s.object_pos),
      });
    }
    if (!subject && s.fault) {
      ctx.fillStyle = "rgba(198,40,40,0.9)";
      ctx.font = `bold ${16 * dpr}px system-ui, sans-serif`;
      ctx.fillText("FAULT: forces off", 12 * dpr, 24 * dpr);
    }
  }

  // -- force traces ----------------------------------------------------------------------

  function drawTraces() {
    const canvas = $("traces");
    const ctx = canvas.getContext("2d");
    const dpr = fit(canvas);
    const W = canvas.width;
    const H = canvas.height;
    ctx.clearRect(0, 0, W, H);
    const tr = state.traces;
    const left = 34 * dpr;
    const bottom = H - 16 * dpr;
    const top = 6 * dpr;
    let fmax = 0;
    for (const p of tr) for (const f of p.full.concat(p.rend)) fmax = Math.max(fmax, f);
    const ymax = fmax <= 1 ? 1 : Math.ceil(fmax);
    ctx.strokeStyle = "#d0d5dd";
    ctx.fillStyle = "#667085";
    ctx.font = `${10 * dpr}px system-ui, sans-serif`;
    ctx.lineWidth = 1;
    for (const frac of [0, 0.5, 1]) {
      const y = bottom - frac * (bottom - top);
      ctx.beginPath();
      ctx.moveTo(left, y);
      ctx.lineTo(W, y);
      ctx.stroke();
      ctx.fillText(`${(frac * ymax).toFixed(ymax < 2 ? 1 : 0)} N`, 2 * dpr, y + 3 * dpr);
    }
    ctx.fillText(`-${TRACE_S} s`, left, H - 3 * dpr);
    ctx.fillText("now", W - 22 * dpr, H - 3 * dpr);
    if (!tr.length) return;
    const tEnd = tr[tr.length - 1].t;
    const x = (t) => left + ((t - (tEnd - TRACE_S)) / TRACE_S) * (W - left);
    const y = (f) => bottom - (f / ymax) * (bottom - top);
    const nf = tr[tr.length - 1].full.length;
    for (let i = 0; i < nf; i++) {
      ctx.strokeStyle = FINGER_COLOURS[i % FINGER_COLOURS.length];
      ctx.lineWidth = 1.5 * dpr;
      for (const [which, dash] of [["full", []], ["rend", [5 * dpr, 3 * dpr]]]) {
        ctx.setLineDash(dash);
        ctx.beginPath();
        tr.forEach((p, k) => (k ? ctx.lineTo(x(p.t), y(p[which][i])) : ctx.moveTo(x(p.t), y(p[which][i]))));
        ctx.stroke();
      }
      ctx.setLineDash([]);
      const name = ((state.status && state.status.fingers) || [])[i] || `finger ${i}`;
      ctx.fillStyle = FINGER_COLOURS[i % FINGER_COLOURS.length];
      ctx.fillText(name, left + 6 * dpr + i * 60 * dpr, top + 10 * dpr);
    }
  }

  // -- interaction and the drawing loop ---------------------------------------------------

  const canvas = $("scene");
  let drag = null;
  // A press on a virtual fingertip moves it (in the plane facing the camera, through where
  // it is); anywhere else turns the camera.
  canvas.addEventListener("pointerdown", (e) => {
    const dpr = window.devicePixelRatio || 1;
    const rect = canvas.getBoundingClientRect();
    const i = subject ? -1 : pickFinger((e.clientX - rect.left) * dpr, (e.clientY - rect.top) * dpr);
    drag = { x: e.clientX, y: e.clientY };
    if (i >= 0) {
      const start = targetOf(i);
      const q = lastView.project(state.sample.device_pos[i]);
      drag.finger = { i, start, z: q ? q.z : cam.dist, x0: e.clientX, y0: e.clientY, view: lastView };
    }
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) {
      const dpr = window.devicePixelRatio || 1;
      const rect = canvas.getBoundingClientRect();
      const over = !subject && pickFinger((e.clientX - rect.left) * dpr, (e.clientY - rect.top) * dpr) >= 0;
      canvas.classList.toggle("virtual-hover", over);
      return;
    }
    if (drag.finger) {
      const f = drag.finger;
      const k = (f.z * (window.devicePixelRatio || 1)) / f.view.focal; // m per CSS pixel
      const delta = add(scale(f.view.right, (e.clientX - f.x0) * k), scale(f.view.up, -(e.clientY - f.y0) * k));
      moveTo(f.i, add(f.start, delta));
      return;
    }
    cam.az -= (e.clientX - drag.x) * 0.01;
    cam.el = Math.min(1.5, Math.max(-0.3, cam.el + (e.clientY - drag.y) * 0.01));
    drag = { x: e.clientX, y: e.clientY };
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    cam.dist = Math.min(2, Math.max(0.06, cam.dist * Math.exp(e.deltaY * 0.001)));
  }, { passive: false });
  canvas.addEventListener("dblclick", () => Object.assign(cam, DEFAULT_CAM));

  function frame() {
    state.frames += 1;
    canvas.dataset.frames = String(state.frames);
    if (!subject) chooseArrowScale();
    drawScene();
    if (!subject) drawTraces();
    if (!subject) showVirtual();
    requestAnimationFrame(frame);
  }
  requestAnimationFrame(frame);
  connect();
})();
