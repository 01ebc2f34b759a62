// The aoi3d console page: state pushed by /events (Server-Sent Events), drawn with plain SVG;
// controls call the services through the console's /api/<service>/<path>. No framework.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";
// timelines: [key, label, colour]; the keys and labels are aoi3d/metric.py's LIVE, in its
// order, each labelled "label (unit)" (tests/unit/domain/test_metric.py holds them to it)
const SERIES = [
  ["psnr_db", "PSNR (dB)", "#4fc3f7"], ["psnr_dynamic_db", "dynamic-region PSNR (dB)", "#81c784"],
  ["ssim", "SSIM", "#fff176"], ["lpips", "LPIPS", "#ff8a65"], ["reward", "reward", "#ce93d8"],
];
// a companion drawn on a timeline's axes: [key, label, colour]; its keys are metric.py's
// LIVE_AT_DISPLAY (the PSNR at display time beside the PSNR at the decision's time)
const COMPANIONS = {"psnr_db": ["psnr_display_db", "at display", "#ffb74d"]};
let lastRender = null;
let state = null;

function el(tag, attrs, parent) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

function facts(dl, pairs) {
  dl.replaceChildren();
  for (const [k, v] of pairs) {
    const dt = document.createElement("dt"); dt.textContent = k;
    const dd = document.createElement("dd"); dd.textContent = v;
    dl.append(dt, dd);
  }
}

const fmt = (x, d = 1) => (x === null || x === undefined || Number.isNaN(x) ? "–" : Number(x).toFixed(d));

// The site shown: ?site=<name> (the run's first site when absent); its pages and the per-site
// services' calls go under /sites/<site>/ (the first site's also at the root).
const SITE = new URLSearchParams(location.search).get("site");
const base = () => (SITE ? `/sites/${encodeURIComponent(SITE)}` : "");
const sitePath = (path) => (SITE ? `sites/${encodeURIComponent(SITE)}/${path}` : path);

function headers() {
  const h = { "content-type": "application/json" };
  const token = localStorage.getItem("aoi3d-token");
  if (token) h.authorization = `Bearer ${token}`;
  return h;
}

async function call(method, service, path, body) {
  const r = await fetch(`/api/${service}/${path}`, {
    method, headers: headers(), body: body === undefined ? undefined : JSON.stringify(body),
  });
  let doc = null;
  try { doc = await r.json(); } catch (e) { doc = null; }
  if (!r.ok) {
    const detail = doc && doc.detail;
    const text = typeof detail === "string" ? detail
      : Array.isArray(detail) ? detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ")
      : `HTTP ${r.status}`;
    throw new Error(text);
  }
  return doc;
}

function say(id, text, ok) {
  const m = $(id);
  m.textContent = text;
  m.className = `msg ${ok ? "ok" : "error"}`;
}

// ---------------------------------------------------------------- drawing
function drawImages(s) {
  const r = s.render;
  if (!r) return;
  $("render-time").textContent = `t = ${fmt(r.time_ms / 1000, 2)} s (decision ${r.decision_id}, ${r.n_views} views, ${r.carry})`;
  $("truth-time").textContent = r.truth_time_ms === null ? "(none of that time yet)" : `t = ${fmt(r.truth_time_ms / 1000, 2)} s`;
  if (r.decision_id !== lastRender) {
    lastRender = r.decision_id;
    const q = `?d=${r.decision_id}`;
    $("render").src = `${base()}/render.png${q}`;
    if (r.truth_time_ms !== null) { $("truth").src = `${base()}/truth.png${q}`; $("diff").src = `${base()}/diff.png${q}`; }
  }
}

function currentMat(s) {
  const p = s.policy;
  return p && p.kind === "mat" ? p.mat_ms : null;
}

function drawAoI(s) {
  const svg = $("aoi");
  svg.replaceChildren();
  const d = s.decision;
  if (!d) return;
  const W = 720, H = 180, pad = 28;
  const mat = currentMat(s);
  const finite = d.aoi_ms.filter((a) => a !== null);
  const top = Math.max(100, mat || 0, ...finite) * 1.1;
  const bw = (W - pad) / d.camera_ids.length;
  const y = (v) => H - 18 - (v / top) * (H - 30);
  const used = new Set(d.selected);
  d.camera_ids.forEach((cam, i) => {
    const a = d.aoi_ms[i];
    const x = pad + i * bw + 2;
    if (a === null) {
      el("rect", { x, y: y(top * 0.9), width: bw - 4, height: H - 18 - y(top * 0.9), class: "bar-unknown" }, svg);
    } else {
      el("rect", { x, y: y(a), width: bw - 4, height: H - 18 - y(a),
        class: used.has(cam) ? "bar-used" : "bar-unused", "data-camera": cam, "data-aoi": a,
        "data-used": used.has(cam) ? "1" : "0" }, svg);
    }
    el("text", { x: x + bw / 2 - 6, y: H - 4 }, svg).textContent = cam;
  });
  for (const v of [0, top / 2]) el("text", { x: 0, y: y(v) + 4 }, svg).textContent = `${Math.round(v)}`;
  if (mat !== null) {
    el("line", { x1: pad, x2: W, y1: y(mat), y2: y(mat), class: "mat-line", id: "mat-line" }, svg);
    el("text", { x: W - 90, y: y(mat) - 4 }, svg).textContent = `Γ = ${mat} ms`;
  }
}

function drawChannel(s) {
  const c = s.channel_summary;
  const t = s.dispatcher || {};
  facts($("channel"), c ? [
    ["delay", c.delay],
    ...(c.in_force && c.in_force !== c.delay ? [["in force now", c.in_force]] : []),
    ["measured delay (mean, last 3 s)", c.measured_delay_ms === null || c.measured_delay_ms === undefined
      ? "–" : `${fmt(c.measured_delay_ms, 1)} ms`],
    ["delivered / s", fmt(c.delivered_per_s, 1)],
    ["drop ratio", fmt(c.drop_ratio, 3)],
    ["delay p50 / p90 / p99 (configured)", c.delay_quantiles_ms
      ? ["0.5", "0.9", "0.99"].map((q) => fmt(c.delay_quantiles_ms[q], 0)).join(" / ") + " ms" : "–"],
  ] : [["channel", (s.channel && s.channel.error) || "–"]]);
  const p = t.pool || {};
  const busy = (p.workers || []).map((w) => w.busy_fraction === null ? "–" : fmt(w.busy_fraction, 2));
  const lost = Object.values(p.lost || {}).reduce((a, b) => a + b, 0);
  facts($("dispatcher"), [
    ["backend", t.backend || "–"], ["worker training steps / s", fmt(t.steps_per_s, 1)],
    ["views", t.n_views ?? "–"], ["render age", s.render ? `${fmt(s.render.age_s, 1)} s` : "–"],
    ["renders", t.renders ?? "–"],
    ["workers", p.workers ? `${p.workers.length}` + (busy.length ? ` (busy ${busy.join(" / ")})` : "") : "–"],
    ["renders / s", fmt(p.renders_per_s, 2)],
    ["decisions rendered", p.rendered_fraction === null || p.rendered_fraction === undefined
      ? "–" : `${fmt(100 * p.rendered_fraction, 0)} %`],
    ["wait to start", p.wait_s_mean === null || p.wait_s_mean === undefined ? "–" : `${fmt(p.wait_s_mean, 2)} s`],
    ["decisions lost", p.lost ? `${lost}` : "–"],
  ]);
  drawLedger(s.ledger || {});
  drawDisplay(s.display || {});
  $("policy-now").textContent = s.decision ? `policy ${s.decision.policy}` : "";
  $("delay-now").textContent = c ? `delay ${c.delay}` : "";
}

// What the viewer sees, and when: the lag from a decision to its render on screen (measured,
// and the scheduler's expectation), the PSNR then beside the PSNR at the decision's time, and
// the budget in force (the decision's, else the dispatcher's render_steps).
function drawDisplay(v) {
  const ms = (x) => (x === null || x === undefined ? "–" : `${fmt(x, 1)} ms`);
  facts($("display"), [
    ["display lag (median)", v.display_lag_n ? `${ms(v.display_lag_ms)} (last ${v.display_lag_n} renders)` : "–"],
    ["expected lag (scheduler)", ms(v.expected_lag_ms)],
    ["PSNR decision / display", `${fmt(v.psnr_db, 2)} / ${fmt(v.psnr_display_db, 2)} dB`],
    ["budget in force", v.budget_steps === null || v.budget_steps === undefined ? "–"
      : `${v.budget_steps} steps (${v.budget_source === "decision" ? "the decision's" : "the dispatcher's render_steps"})`],
  ]);
}

// The decision ledger (metrics GET /ledger): how every decision of the site ended.
function drawLedger(l) {
  if (l.error || l.decisions === undefined) { facts($("ledger"), [["decision ledger", l.error || "–"]]); return; }
  const pct = (n) => l.decisions ? ` (${fmt(100 * n / l.decisions, 1)} %)` : "";
  const reasons = (o) => Object.entries(o).filter(([, n]) => n > 0).map(([r, n]) => `${r} ${n}`).join(", ");
  const skipped = Object.values(l.skipped).reduce((a, b) => a + b, 0);
  facts($("ledger"), [
    ["decisions", `${l.decisions}`],
    ["scored", `${l.scored}${pct(l.scored)}`],
    ["skipped (newer taken)", `${skipped}${pct(skipped)}`],
    ["lost", `${l.lost_total}${pct(l.lost_total)}` + (l.lost_total ? ` — ${reasons(l.lost)}` : "")],
    ["open", `${l.open}` + (l.oldest_open_s !== null ? ` (oldest ${fmt(l.oldest_open_s, 1)} s)` : "")],
  ]);
}

function drawCharts(s) {
  const box = $("charts");
  box.replaceChildren();
  const qs = s.quality;
  if (!qs.length) { box.textContent = "waiting for the first scored render…"; return; }
  const W = 720, H = 70, t1 = s.wall_s, t0 = Math.min(qs[0].wall_s, t1 - 60);
  const x = (t) => 40 + ((t - t0) / (t1 - t0)) * (W - 50);
  const has = (key) => (q) => q[key] !== null && q[key] !== undefined;
  for (const [key, label, colour] of SERIES) {
    const companion = COMPANIONS[key];
    const pts = qs.filter(has(key));
    const other = companion ? qs.filter(has(companion[0])) : [];
    const svg = el("svg", { width: W, height: H, "data-series": key }, box);
    const newest = (ps, k) => (ps.length ? fmt(ps[ps.length - 1][k], 3) : "–");
    el("text", { x: 40, y: 11 }, svg).textContent = `${label}: ${newest(pts, key)}` +
      (companion ? ` · ${companion[1]}: ${newest(other, companion[0])}` : "");
    if (!pts.length) continue;
    const vals = pts.map((q) => q[key]).concat(other.map((q) => q[companion[0]]));
    let lo = Math.min(...vals), hi = Math.max(...vals);
    if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
    const y = (v) => H - 6 - ((v - lo) / (hi - lo)) * (H - 22);
    el("text", { x: 0, y: y(hi) + 4 }, svg).textContent = fmt(hi, 2);
    el("text", { x: 0, y: y(lo) + 4 }, svg).textContent = fmt(lo, 2);
    const line = (ps, k, c, cls) => el("polyline", { class: cls, stroke: c, "data-key": k,
      points: ps.map((q) => `${x(q.wall_s).toFixed(1)},${y(q[k]).toFixed(1)}`).join(" ") }, svg);
    line(pts, key, colour, "series");
    if (other.length) line(other, companion[0], companion[2], "series companion");
    for (const m of s.markers) {
      el("line", { x1: x(m.wall_s), x2: x(m.wall_s), y1: 14, y2: H, class: "marker" }, svg);
      el("title", {}, svg).textContent = m.text;
    }
  }
  drawGamma(s, box, W, H, x);
}

// Γ in force per decision (an adaptive policy's follows the channel): its own series, apart
// from the channel's estimated delay, on the quality charts' time axis.
function drawGamma(s, box, W, H, x) {
  const pts = (s.gamma || []).filter((g) => g.gamma_ms !== null && g.gamma_ms !== undefined
                                           && g.wall_s >= s.wall_s - 600);
  const svg = el("svg", { width: W, height: H, "data-series": "gamma_ms" }, box);
  const now = pts.length ? pts[pts.length - 1] : null;
  el("text", { x: 40, y: 11 }, svg).textContent =
    `Γ in force (ms): ${now ? fmt(now.gamma_ms, 0) + " — " + now.policy : "– (the policy has no Γ)"}`;
  if (!pts.length) return;
  const vals = pts.map((g) => g.gamma_ms);
  let lo = Math.min(0, ...vals), hi = Math.max(...vals);
  if (hi - lo < 1e-9) { hi = lo + 1; }
  const y = (v) => H - 6 - ((v - lo) / (hi - lo)) * (H - 22);
  el("text", { x: 0, y: y(hi) + 4 }, svg).textContent = fmt(hi, 0);
  el("text", { x: 0, y: y(lo) + 4 }, svg).textContent = fmt(lo, 0);
  // a step line: Γ holds until the next decision that changed it
  const xy = [];
  pts.forEach((g, i) => {
    if (i > 0) xy.push(`${x(g.wall_s).toFixed(1)},${y(pts[i - 1].gamma_ms).toFixed(1)}`);
    xy.push(`${x(g.wall_s).toFixed(1)},${y(g.gamma_ms).toFixed(1)}`);
  });
  xy.push(`${x(s.wall_s).toFixed(1)},${y(now.gamma_ms).toFixed(1)}`);
  el("polyline", { class: "series", stroke: "#8a5cf6", points: xy.join(" ") }, svg);
  for (const m of s.markers) {
    el("line", { x1: x(m.wall_s), x2: x(m.wall_s), y1: 14, y2: H, class: "marker" }, svg);
    el("title", {}, svg).textContent = m.text;
  }
}

// The channel over time: the measured mean delay (delivery − generation over the network's
// last 3 s) and the mean of the spec in force (a step at every regime change), with the
// channel markers. Other series (an adaptive policy's Γ) can be drawn on the same axes.
function drawChannelChart(s) {
  const svg = $("channel-chart");
  if (!svg) return;
  svg.replaceChildren();
  const pts = s.channel_series || [];
  const W = 720, H = 110;
  if (!pts.length) { el("text", { x: 40, y: 14 }, svg).textContent = "channel: waiting for the network"; return; }
  const t1 = s.wall_s, t0 = Math.min(pts[0].wall_s, t1 - 60);
  const x = (t) => 40 + ((t - t0) / (t1 - t0)) * (W - 50);
  // the adaptive policy's Γ (its own series, from the decisions) on the same ms axis
  const gam = (s.gamma || []).filter((g) => g.gamma_ms !== null && g.gamma_ms !== undefined && g.wall_s >= t0);
  const vals = pts.flatMap((p) => [p.measured_delay_ms, p.in_force_mean_ms]).concat(gam.map((g) => g.gamma_ms)).filter((v) => v !== null && v !== undefined);
  const hi = Math.max(10, ...vals) * 1.1;
  const y = (v) => H - 6 - (v / hi) * (H - 24);
  const last = pts[pts.length - 1];
  el("text", { x: 40, y: 11 }, svg).textContent =
    `delay (ms): measured ${fmt(last.measured_delay_ms, 1)} · in force ${last.in_force}`;
  for (const v of [0, hi / 2]) el("text", { x: 0, y: y(v) + 4 }, svg).textContent = `${Math.round(v)}`;
  const line = (key, cls, step) => {
    const q = pts.filter((p) => p[key] !== null && p[key] !== undefined);
    if (!q.length) return;
    const coords = [];
    q.forEach((p, i) => {
      if (step && i) coords.push(`${x(p.wall_s).toFixed(1)},${y(q[i - 1][key]).toFixed(1)}`);
      coords.push(`${x(p.wall_s).toFixed(1)},${y(p[key]).toFixed(1)}`);
    });
    el("polyline", { class: cls, points: coords.join(" "), "data-series": key }, svg);
  };
  line("in_force_mean_ms", "series regime-mean", true);
  line("measured_delay_ms", "series measured-delay", false);
  if (gam.length) {
    const coords = [];
    gam.forEach((g, i) => {
      if (i) coords.push(`${x(g.wall_s).toFixed(1)},${y(gam[i - 1].gamma_ms).toFixed(1)}`);
      coords.push(`${x(g.wall_s).toFixed(1)},${y(g.gamma_ms).toFixed(1)}`);
    });
    coords.push(`${x(t1).toFixed(1)},${y(gam[gam.length - 1].gamma_ms).toFixed(1)}`);
    el("polyline", { class: "series gamma", stroke: "#8a5cf6", points: coords.join(" "),
                     "data-series": "gamma_ms" }, svg);
    el("text", { x: 420, y: 11 }, svg).textContent = `Γ ${fmt(gam[gam.length - 1].gamma_ms, 0)}`;
  }
  for (const m of (s.markers || []).filter((m) => m.kind === "channel")) {
    el("line", { x1: x(m.wall_s), x2: x(m.wall_s), y1: 14, y2: H, class: "marker" }, svg);
    el("title", {}, svg).textContent = m.text;
  }
}

function draw(s) {
  state = s;
  drawImages(s);
  drawAoI(s);
  drawChannel(s);
  drawChannelChart(s);
  drawCharts(s);
}

// ---------------------------------------------------------------- controls
function showPolicyRows() {
  const kind = $("kind").value;
  $("mat-row").hidden = kind !== "mat";
  $("k-row").hidden = kind !== "freshest";
  $("wait-row").hidden = kind !== "wait";
  $("ppo-row").hidden = kind !== "ppo";
}

function policyKindBody() {
  const kind = $("kind").value;
  if (kind === "mat") return { kind, mat_ms: Number($("mat").value) };
  if (kind === "freshest") return { kind, k: Number($("k").value) };
  if (kind === "wait") return { kind, wait_ms: Number($("wait").value) };
  if (kind === "ppo") return { kind, checkpoint: $("checkpoint").value };
  if (kind.startsWith("adaptive:")) return { kind: "adaptive", mode: kind.slice(9) };
  return { kind };
}

// The policy with its training budget (empty: none, the dispatcher's render_steps); the
// scheduler checks the number and says what is wrong.
function policyBody() {
  const body = policyKindBody();
  const budget = $("budget").value.trim();
  if (budget !== "") body.budget_steps = Number(budget);
  return body;
}

async function applyPolicy() {
  try {
    const p = await call("PUT", "scheduler", sitePath("policy"), policyBody());
    say("policy-msg", `policy ${p.spec}`, true);
  } catch (e) { say("policy-msg", e.message, false); }
}

async function applyDelay(spec) {
  try {
    const c = await call("PUT", "network", sitePath("channel"), { delay: spec });
    say("delay-msg", `delay ${c.delay}`, true);
  } catch (e) { say("delay-msg", e.message, false); }
}

async function setup() {
  const cfg = await (await fetch("/config")).json();
  for (const name of cfg.sites || []) $("site").add(new Option(name, name));
  $("site").value = SITE || (cfg.sites || [""])[0];
  $("site-row").hidden = (cfg.sites || []).length < 2;
  $("site").addEventListener("change", () => {
    location.search = `?site=${encodeURIComponent($("site").value)}`;
  });
  $("token-row").hidden = !cfg.token_required;
  // the 3D viewer (services/viewer) on its own port of the host the page came from
  $("viewer-link").href = `${location.protocol}//${location.hostname}:${cfg.viewer_port}/`;
  $("token").value = localStorage.getItem("aoi3d-token") || "";
  $("token").addEventListener("change", () => localStorage.setItem("aoi3d-token", $("token").value));
  try {
    const list = await call("GET", "scheduler", "policy/checkpoints");
    for (const c of list.checkpoints) $("checkpoint").add(new Option(c, c));
  } catch (e) { $("checkpoint").add(new Option("(none found)", "")); }
  try {
    const p = await call("GET", "scheduler", sitePath("policy"));
    $("kind").value = p.kind;
    if (p.kind === "mat") { $("mat").value = p.mat_ms; $("mat-value").textContent = p.mat_ms; }
    $("budget").value = p.budget_steps ?? "";
    const t = await call("GET", "dispatcher", "status");  // its backends: the choices
    for (const b of t.backends) $("backend").add(new Option(b, b));
    $("backend").value = t.backend;
  } catch (e) { /* shown by the next event */ }
  showPolicyRows();
  $("kind").addEventListener("change", showPolicyRows);
  $("mat").addEventListener("input", () => { $("mat-value").textContent = $("mat").value; });
  $("mat").addEventListener("change", applyPolicy);  // a slider move applies at release
  $("apply-policy").addEventListener("click", applyPolicy);
  $("delay-mean").addEventListener("input", () => { $("delay-mean-value").textContent = $("delay-mean").value; });
  $("delay-mean").addEventListener("change", () => applyDelay(`exp:${$("delay-mean").value}`));
  $("apply-delay").addEventListener("click", () => applyDelay($("delay-spec").value || `exp:${$("delay-mean").value}`));
  $("apply-backend").addEventListener("click", async () => {
    try {
      await call("PUT", "dispatcher", "backend", { backend: $("backend").value });
      say("model-msg", `backend ${$("backend").value}`, true);
    } catch (e) { say("model-msg", e.message, false); }
  });
  $("reset").addEventListener("click", async () => {
    try { await call("POST", "dispatcher", "reset"); say("model-msg", "model reset", true); }
    catch (e) { say("model-msg", e.message, false); }
  });

  const events = new EventSource(`${base()}/events`);
  events.onopen = () => { $("conn").textContent = "live"; $("conn").className = "pill ok"; };
  events.onerror = () => { $("conn").textContent = "reconnecting…"; $("conn").className = "pill bad"; };
  events.onmessage = (ev) => draw(JSON.parse(ev.data));
}

setup();
