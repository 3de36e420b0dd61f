// SpatialAnt dashboard: plain JS against the gateway's API (no build step).
// Everything user-provided is inserted with textContent, never innerHTML.
"use strict";

const $ = (sel) => document.querySelector(sel);
const el = (tag, cls, text) => {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
};
const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
const METRIC_NAMES = { ne_m: "NE (m)", osr: "OSR", sr: "SR", spl: "SPL", ndtw: "nDTW", sdtw: "SDTW", tl_m: "TL (m)" };

let current = null;      // id of the mission on screen
let stream = null;       // its EventSource
let record = null;       // its record, kept up to date from events

// The token (read or API) lives in this tab's sessionStorage only. It comes from the Access token
// field, or from a link like /dashboard#token=...: taken out of the address bar at once, so it is
// neither bookmarked nor sent anywhere but in our own requests.
const TOKEN_KEY = "ant-token";
function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }
function setToken(t) { if (t) sessionStorage.setItem(TOKEN_KEY, t); else sessionStorage.removeItem(TOKEN_KEY); }
(function tokenFromFragment() {
  const m = location.hash.match(/^#token=([^&]*)/);
  if (!m) return;
  setToken(decodeURIComponent(m[1]));
  history.replaceState(null, "", location.pathname + location.search);
})();
// An EventSource, an <img> or a download link cannot send a header: the gateway takes the token as
// ?access_token= there (and the gateway's access log leaves it out).
function withToken(url) {
  if (!url || !token() || url.startsWith("data:")) return url;
  return url + (url.includes("?") ? "&" : "?") + "access_token=" + encodeURIComponent(token());
}
function authHeaders(headers = {}) {
  if (token()) headers["Authorization"] = "Bearer " + token();
  return headers;
}

// 3 -> "3 pts", 48210 -> "48.2k pts", 2.1e6 -> "2.1M pts" (a 3-point map is not "0.0k").
function points(n) {
  if (n < 1000) return `${n} pts`;
  return n < 1e6 ? `${(n / 1000).toFixed(1)}k pts` : `${(n / 1e6).toFixed(1)}M pts`;
}

async function api(path, opts = {}) {
  const headers = Object.assign({ "Accept": "application/json" }, opts.headers || {});
  if (opts.body) headers["Content-Type"] = "application/json";
  authHeaders(headers);  // reads too: with ANT_READ_TOKEN set, every GET needs it
  const r = await fetch(path, Object.assign({}, opts, { headers }));
  let body = null;
  try { body = await r.json(); } catch (_) { /* empty or not JSON */ }
  if (!r.ok) {
    let detail = body && body.detail;
    if (Array.isArray(detail)) detail = detail.map((d) => `${(d.loc || []).slice(1).join(".")}: ${d.msg}`).join("; ");
    if (r.status === 401) $("#token-box").open = true;  // say where the token goes
    throw new Error(`${r.status}: ${detail || r.statusText}`);
  }
  return body;
}

// --- services, maps, missions -------------------------------------------------------------------
async function refreshStatus() {
  const box = $("#services");
  try {
    const s = await api("/status");
    const seen = new Map(s.services.map((x) => [x.service, x]));
    box.replaceChildren(...s.expected.map((name) => {
      const svc = seen.get(name);
      const p = el("span", "pill " + (svc ? "up" : "down"), svc ? `${name} ×${svc.instances}` : `${name} down`);
      if (svc && svc.details[0]) p.title = `version ${svc.details[0].version || "?"}`;
      return p;
    }));
  } catch (e) {
    box.replaceChildren(el("span", "pill down", "status unavailable"));
  }
}

// Issue 33: a built map says whether it was corrected for odometry drift, and how much.
function driftLabel(d) {
  if (!d) return "";
  if (!d.applied) return " · built without drift correction";
  // The mapper's own localisation first: on a robot without a localiser it placed most of the map.
  const odom = d.odom_regions_corrected ? `${d.odom_regions_corrected} tours localised (median ` +
    `${(+d.odom_median_correction_m).toFixed(2)} m, max ${(+d.odom_max_correction_m).toFixed(2)} m), ` : "";
  const g = d.pose_graph;
  const graph = g && g.applied ? `pose graph over ${g.panoramas} panoramas (${g.loop_closures_accepted} loop closures, ` +
    `${g.loop_closures_rejected} rejected` +
    (g.weak_edges ? `; ${g.weak_edges} of ${g.scan_edges} edges pinned one way` : "") +
    (g.nodes_moved ? `; ${g.nodes_moved} graph nodes moved with them, max ` +
    `${(+g.max_node_shift_m).toFixed(2)} m` : "") + "), " : "";
  return ` · drift corrected: ${odom}${graph}${d.regions_corrected} regions moved (max ${(+d.max_correction_m).toFixed(2)} m, ` +
    `${(+d.max_correction_deg).toFixed(1)}°), ${d.regions_fallback} kept odometry`;
}

function driftDetails(d) {
  if (!d || !d.applied) return "";
  const rows = (d.per_region || []).map((r) => `\nregion ${r.region}: ` + (r.anchor ? "anchor" :
    r.fell_back ? `kept odometry (${r.reason})` : `${(+r.correction_m).toFixed(3)} m ${(+r.correction_deg).toFixed(2)}°` +
    (r.rmse_m != null ? `, rmse ${(100 * r.rmse_m).toFixed(1)} cm` : "")) +
    (r.frames_registered || r.frames_fallback ? `, frames ${r.frames_registered} registered / ${r.frames_fallback} odometry` : ""));
  return `\ndrift correction (${d.method || "frames"}), loop closures ${d.loop_closures_accepted} accepted / ` +
    `${d.loop_closures_rejected} rejected` + rows.join("");
}

async function refreshMaps() {
  const list = $("#maps"), select = $("#map-select");
  try {
    const maps = await api("/maps");
    const keep = select.value;
    select.replaceChildren(...maps.map((m) => { const o = el("option", "", m.map_id); o.value = m.map_id; return o; }));
    if (keep && maps.some((m) => m.map_id === keep)) select.value = keep;
    list.replaceChildren(...(maps.length ? maps.map((m) => {
      const li = el("li");
      li.append(el("span", "text", m.map_id),
        el("span", "meta", `${points(m.point_count)} · v${m.version}` + driftLabel(m.drift_correction)));
      li.title = `source ${m.source || "?"}${driftDetails(m.drift_correction)}; click to download the cloud`;
      li.onclick = () => { window.location.href = withToken(`/maps/${encodeURIComponent(m.map_id)}/cloud.ply`); };
      li.append(mapDownloads(m.map_id));
      return li;
    }) : [el("li", "muted", "no maps yet")]));
  } catch (e) {
    list.replaceChildren(el("li", "muted", "maps unavailable (" + e.message + ")"));
  }
}

async function refreshMissions() {
  const state = $("#state-filter").value;
  try {
    const page = await api("/missions?limit=50" + (state ? "&state=" + state : ""));
    $("#missions").replaceChildren(...(page.items.length ? page.items.map((m) => {
      const li = el("li");
      li.dataset.id = m.id;
      if (m.id === current) li.classList.add("active");
      li.append(el("span", "dot " + m.state), el("span", "text", m.instruction),
        el("span", "meta", `${m.state} · ${m.step}`));
      li.title = `${m.id} on ${m.map_id}`;
      li.onclick = () => select(m.id);
      return li;
    }) : [el("li", "muted", "no missions yet")]));
  } catch (e) { /* keep the last list */ }
}

// --- downloads ------------------------------------------------------------------------------------
function link(name, url, title) {
  const a = el("a", "dl", name);
  a.href = withToken(url); a.setAttribute("download", ""); if (title) a.title = title;
  a.onclick = (e) => e.stopPropagation();  // inside a clickable list row
  return a;
}

function mapDownloads(mapId) {
  const base = `/maps/${encodeURIComponent(mapId)}`, box = el("span", "downloads");
  box.append(link("PLY", `${base}/cloud.ply`, "binary PLY cloud"), link("PCD", `${base}/cloud.pcd`, "binary PCD cloud"),
    link("Nav2", `${base}/nav2.zip`, "Nav2 map_server map (PGM + YAML) of the lowest floor"));
  return box;
}

async function renderDownloads(kind, id) {
  const box = $("#m-downloads");
  try {
    const list = await api(`/${kind}s/${encodeURIComponent(id)}/downloads`);
    if (current !== id) return;
    box.replaceChildren(...list.items.map((d) => d.available ? link(d.name, d.url)
      : el("span", "dl off", d.name + " - " + d.reason)));
  } catch (e) { box.replaceChildren(el("span", "muted", "downloads unavailable (" + e.message + ")")); }
}

// --- one mission ------------------------------------------------------------------------------------
function setImage(img, url) { url = withToken(url); if (url && img.getAttribute("src") !== url) img.src = url; }

function renderHead() {
  $("#mission").classList.remove("empty");
  $("#m-title").textContent = `Mission ${record.id}`;
  $("#m-instruction").textContent = record.instruction || "";
  const badge = $("#m-state");
  badge.textContent = record.state;
  badge.className = "badge " + record.state;
  // Steps taken: the decisions seen so far (the decision box numbers the same decisions the same way).
  $("#m-step").textContent = `step ${record.decisions_seen}`;
  $("#cancel").hidden = TERMINAL.has(record.state);
  // How it ended is not whether it was right: success exists only when the mission had a goal.
  const outcome = $("#m-outcome");
  outcome.hidden = !record.outcome;
  if (record.outcome) {
    // "arrived" only when the success criterion held (issue 32): the policy stopping is not arriving.
    const goal = record.success === true ? "arrived" : record.success === false ? "did not arrive" : "no goal given";
    const ne = record.metrics && typeof record.metrics.ne_m === "number" ? ` · NE ${record.metrics.ne_m.toFixed(1)} m` : "";
    outcome.textContent = `${OUTCOMES[record.outcome] || record.outcome} · ${goal}${ne}`;
    outcome.className = "badge outcome " + (record.success === true ? "ok" : record.success === false ? "miss" : "");
  }
}

const OUTCOMES = { policy_stopped: "policy stopped", no_way_to_move: "no way to move", max_steps: "step budget used up",
                   cancelled: "cancelled", failed: "failed" };

function renderImages(images) {
  setImage($("#panorama"), images.panorama);
  setImage($("#spatial-map"), images.map);
  drawTrajectory(!images.map);
}

function drawTrajectory(visible) {
  // The planner's spatial map already shows the trajectory; draw our own only when it has none.
  const c = $("#traj"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const t = record.trajectory || [];
  if (!visible || t.length < 1) return;
  const xs = t.map((p) => p[0]), ys = t.map((p) => p[1]);
  const span = Math.max(2, Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys));
  const s = (c.width - 40) / span, cx = (Math.max(...xs) + Math.min(...xs)) / 2, cy = (Math.max(...ys) + Math.min(...ys)) / 2;
  const px = (p) => [c.width / 2 + (p[0] - cx) * s, c.height / 2 - (p[1] - cy) * s];
  g.strokeStyle = "#4f9cff"; g.lineWidth = 3; g.beginPath();
  t.forEach((p, i) => { const [x, y] = px(p); i ? g.lineTo(x, y) : g.moveTo(x, y); });
  g.stroke();
  const [x, y] = px(t[t.length - 1]);
  g.fillStyle = "#ff5d6c"; g.beginPath(); g.arc(x, y, 6, 0, 2 * Math.PI); g.fill();
}

function renderDecision(decision, extra) {
  const box = $("#decision");
  if (!decision) return;
  const choice = decision.kind === "stop" ? "Stop" :
    decision.kind === "backtrack" ? "Backtrack" : `Go to candidate ${decision.candidate_index}`;
  const reason = el("p", "reason", decision.reasoning || "(no reasoning given)");
  const tokens = el("div", "tokens",
    `${decision.backend || "policy"} · ${record.prompt_tokens} prompt + ${record.completion_tokens} completion tokens` +
    ` · $${(record.cost_usd || 0).toFixed(4)}` + (decision.fallback ? " · fallback" : ""));
  box.replaceChildren(el("div", "choice", `Step ${decision.step}: ${choice}`), reason, tokens);
  if (extra && extra.timings_s) {
    const t = Object.entries(extra.timings_s).map(([k, v]) => `${k} ${(+v).toFixed(2)} s`).join(" · ");
    box.append(el("div", "tokens", t));
  }
}

function renderMetrics(metrics) {
  const body = $("#metrics tbody");
  if (!metrics) {
    const tr = el("tr");
    tr.append(el("td", "muted", TERMINAL.has(record.state) ? "no goal given: no metrics" : "reported at the end"));
    body.replaceChildren(tr);
    return;
  }
  body.replaceChildren(...Object.entries(metrics).map(([k, v]) => {
    const tr = el("tr");
    tr.append(el("td", "", METRIC_NAMES[k] || k), el("td", "", typeof v === "number" ? v.toFixed(3) : String(v)));
    return tr;
  }));
}

function renderCandidates(candidates, images, chosen) {
  const box = $("#candidates");
  const cards = (candidates || []).filter((c) => (c.kind || "waypoint") === "waypoint").map((c) => {
    const card = el("div", "cand" + (c.index === chosen ? " chosen" : ""));
    card.dataset.index = c.index;
    const title = el("div", "title");
    title.append(el("b", "", `#${c.index}${c.index === chosen ? " · chosen" : ""}`),
      el("span", "", `${(+c.distance_m || 0).toFixed(1)} m · ${((+c.angle_rad || 0) * 180 / Math.PI).toFixed(0)}°`));
    const views = el("div", "views");
    for (const [kind, label] of [["observed", "observed"], ["anticipated", "anticipated"]]) {
      const f = el("figure"), img = el("img");
      img.alt = `candidate ${c.index} ${label}`;
      const url = images[`cand_${c.index}_${kind}`];
      if (url) img.src = withToken(url);
      f.append(img, el("figcaption", "", label));
      views.append(f);
    }
    card.append(title, views);
    return card;
  });
  box.replaceChildren(...(cards.length ? cards : [el("p", "muted", "no candidates yet")]));
}

function addStep(ev) {
  const d = ev.data || {};
  let text = ev.kind;
  if (d.decision) text = d.decision.kind === "stop" ? "stop" : `go to #${d.decision.candidate_index}`;
  if (ev.kind === "finished") text = `finished: ${ev.state}`;
  if (ev.kind === "error") text = `error: ${d.error || d.message || ""}`;
  const li = el("li");
  li.dataset.seq = ev.seq;
  li.append(el("span", "k", ev.kind === "step" ? `step ${ev.ordinal}` : ev.kind), el("span", "", text));
  if (d.decision && d.decision.reasoning) li.title = d.decision.reasoning;
  $("#steps").append(li);
  li.scrollIntoView({ block: "nearest" });
}

function onEvent(ev) {
  if (!record || ev.mission_id !== record.id) return;
  if (ev.seq <= record._seen) return;
  record._seen = ev.seq;
  record.state = ev.state; record.step = ev.step;
  // The n-th decision is step n everywhere on the page, however the planner numbers its events.
  if (ev.kind === "step") ev.ordinal = ++record.decisions_seen;
  const d = ev.data || {};
  if (d.pose && d.pose.position_m) {
    const t = record.trajectory, p = d.pose.position_m;
    if (!t.length || t[t.length - 1].join() !== p.join()) t.push(p);
  }
  if (d.decision) {
    record.prompt_tokens += d.decision.prompt_tokens || 0;
    record.completion_tokens += d.decision.completion_tokens || 0;
    record.cost_usd += d.decision.cost_usd || 0;
  }
  if (d.metrics) record.metrics = d.metrics;
  Object.assign(record.images, ev.images || {});
  if (TERMINAL.has(ev.state)) {
    // The outcome and success are the gateway's reading of the end: take them from the record.
    api(`/missions/${record.id}`).then((r) => { record.outcome = r.outcome; record.success = r.success; record.metrics = r.metrics || record.metrics; renderHead(); })
      .catch(() => {});
  }
  renderHead();
  renderImages(record.images);
  if (d.candidates) {
    record.candidates = d.candidates;
    renderCandidates(d.candidates, ev.images || {}, d.decision ? d.decision.candidate_index : null);
  }
  if (d.decision) renderDecision(Object.assign({ step: ev.ordinal }, d.decision), d);
  renderMetrics(record.metrics);
  addStep(ev);
  if (d.pose) drawSceneGraph();
}

async function select(id) {
  if (stream) { stream.close(); stream = null; }
  current = id;
  history.replaceState(null, "", "#" + id);
  document.querySelectorAll("#missions li").forEach((li) => li.classList.toggle("active", li.dataset.id === id));
  $("#steps").replaceChildren();
  $("#decision").replaceChildren(el("p", "muted", "Waiting for the first step."));
  $("#candidates").replaceChildren();
  try {
    record = await api(`/missions/${encodeURIComponent(id)}`);
  } catch (e) { $("#form-error").textContent = e.message; return; }
  // The stream replays every event from the start, so the view is built from events alone.
  Object.assign(record, { _seen: -1, decisions_seen: 0, trajectory: [], images: {}, prompt_tokens: 0,
                          completion_tokens: 0, cost_usd: 0 });
  renderHead();
  renderMetrics(record.metrics);
  renderDownloads("mission", id);
  loadSceneGraph(record.map_id);
  stream = new EventSource(withToken(`/missions/${encodeURIComponent(id)}/events`));
  const handler = (msg) => onEvent(JSON.parse(msg.data));
  for (const k of ["started", "step", "progress", "finished", "error"]) stream.addEventListener(k, handler);
  stream.addEventListener("end", () => { stream.close(); stream = null; refreshMissions(); renderDownloads("mission", id); });
}

async function submit(e) {
  e.preventDefault();
  const err = $("#form-error"), btn = $("#submit");
  err.textContent = "";
  setToken($("#token").value.trim());
  const body = {
    instruction: $("#instruction").value.trim(), map_id: $("#map-select").value,
    options: { policy: $("#policy").value.trim() || "heuristic", max_steps: parseInt($("#max-steps").value, 10) || 40 },
  };
  if ($("#record").checked) body.options.record = true;
  if (!body.instruction) { err.textContent = "write an instruction first"; return; }
  if (!body.map_id) { err.textContent = "no map to navigate: explore or upload one first"; return; }
  btn.disabled = true;
  try {
    const created = await api("/missions", { method: "POST", body: JSON.stringify(body) });
    await refreshMissions();
    await select(created.id);
  } catch (ex) { err.textContent = ex.message; } finally { btn.disabled = false; }
}

async function cancel() {
  if (!current) return;
  try { await api(`/missions/${encodeURIComponent(current)}/cancel`, { method: "POST" }); }
  catch (e) { $("#form-error").textContent = e.message; }
}

// --- explorations and uploads ----------------------------------------------------------------------
let exploreStream = null;
let exploring = null;    // id of the exploration in the explore box

function showExploration(rec) {
  const box = $("#explore-box");
  box.hidden = false;
  box.className = "job " + rec.state;
  $("#explore-progress").value = rec.progress == null ? 0 : rec.progress;
  const pct = rec.progress == null ? "" : ` ${Math.round(100 * rec.progress)}%`;
  // A finished exploration shows how it ended, not the last stage it was in ("reconstructing 10 regions");
  // a cancelled one says which stage the cancel stopped.
  const what = rec.error ? `: ${rec.error}`
    : rec.state === "cancelled" && rec.stage ? ` · while ${rec.stage}`
    : TERMINAL.has(rec.state) ? "" : rec.stage ? ` · ${rec.stage}` : "";
  // While exploring, the message is the step's standing (visited, frontiers, coverage, time left):
  // a real robot explores for many minutes and the bar alone would look stuck.
  const detail = !TERMINAL.has(rec.state) && rec.message ? ` · ${rec.message}` : "";
  $("#explore-status").textContent = `${rec.state}${pct}${what}${detail}`;
  $("#explore-status").dataset.state = rec.state;
  $("#explore-cancel").hidden = TERMINAL.has(rec.state);
}

function followExploration(created, mapId) {
  if (exploreStream) exploreStream.close();
  exploring = created.id;
  $("#explore-cancel").disabled = false;
  const rec = { state: "queued", progress: 0, stage: null, message: null, error: null };
  showExploration(rec);
  exploreStream = new EventSource(withToken(created.events_url));
  const handler = (msg) => {
    const ev = JSON.parse(msg.data), data = ev.data || {};
    rec.state = ev.state;
    if (typeof data.progress === "number") rec.progress = Math.min(1, Math.max(0, data.progress));
    if (typeof data.stage === "string") rec.stage = data.stage;
    if (typeof data.message === "string") rec.message = data.message;
    if (ev.kind === "error" || typeof data.error === "string") rec.error = data.error || data.message || "error";
    if (ev.state === "succeeded") rec.progress = 1;
    showExploration(rec);
  };
  for (const k of ["started", "step", "progress", "finished", "error"]) exploreStream.addEventListener(k, handler);
  exploreStream.addEventListener("end", (msg) => {
    exploreStream.close(); exploreStream = null;
    rec.state = JSON.parse(msg.data).state;
    showExploration(rec);
    $("#explore").disabled = false;
    // The new map is ready to navigate: offer it in the mission form.
    refreshMaps().then(() => { if (rec.state === "succeeded") $("#map-select").value = mapId; });
  });
}

async function explore(e) {
  e.preventDefault();
  const err = $("#explore-error"), btn = $("#explore"), mapId = $("#explore-map").value.trim();
  err.textContent = "";
  setToken($("#token").value.trim());
  btn.disabled = true;
  try {
    const created = await api("/explorations", { method: "POST", body: JSON.stringify({ map_id: mapId }) });
    followExploration(created, mapId);
  } catch (ex) { err.textContent = ex.message; btn.disabled = false; }
}

async function cancelExploration() {
  if (!exploring) return;
  const err = $("#explore-error"), btn = $("#explore-cancel");
  err.textContent = "";
  setToken($("#token").value.trim());
  btn.disabled = true;  // once: its cancelled event ends the stream and hides the button
  try { await api(`/explorations/${encodeURIComponent(exploring)}/cancel`, { method: "POST" }); }
  catch (ex) { err.textContent = ex.message; btn.disabled = false; }
}

// An exploration still running when the page opens (started by another tab, or by the evaluation
// runner) is shown, and can be cancelled, as one started here.
async function resumeExploration() {
  try {
    const page = await api("/explorations?state=running&state=queued&limit=1");
    const x = page.items[0];
    if (x && !exploreStream) {
      $("#explore").disabled = true;
      followExploration(x, x.map_id);
    }
  } catch (_) { /* the explore box stays empty */ }
}

async function upload(e) {
  e.preventDefault();
  const err = $("#upload-error"), status = $("#upload-status"), btn = $("#upload");
  const file = $("#upload-file").files[0], mapId = $("#upload-map").value.trim();
  err.textContent = ""; status.textContent = "";
  if (!file) { err.textContent = "choose a .ply or .pcd file"; return; }
  setToken($("#token").value.trim());
  const headers = authHeaders({ "Content-Type": "application/octet-stream", "Accept": "application/json" });
  const url = `/maps?map_id=${encodeURIComponent(mapId)}&filename=${encodeURIComponent(file.name)}`;
  btn.disabled = true;
  status.textContent = `uploading ${(file.size / 1e6).toFixed(1)} MB ...`;
  try {
    const r = await fetch(url, { method: "POST", headers, body: file });
    let body = null;
    try { body = await r.json(); } catch (_) { /* not JSON */ }
    if (!r.ok) throw new Error(`${r.status}: ${(body && JSON.stringify(body.detail)) || r.statusText}`);
    status.textContent = `${body.map_id} v${body.version}: ${body.point_count} points`;
    await refreshMaps();
    $("#map-select").value = body.map_id;
  } catch (ex) { status.textContent = ""; err.textContent = ex.message; } finally { btn.disabled = false; }
}

$("#explore-form").addEventListener("submit", explore);
$("#upload-form").addEventListener("submit", upload);
$("#mission-form").addEventListener("submit", submit);
$("#cancel").addEventListener("click", cancel);
$("#explore-cancel").addEventListener("click", cancelExploration);
$("#state-filter").addEventListener("change", refreshMissions);
$("#token").value = token();
$("#token").addEventListener("change", () => { setToken($("#token").value.trim()); refreshAll(); });
function refreshAll() { refreshStatus(); refreshMaps(); refreshMissions(); }
refreshStatus(); refreshMaps(); resumeExploration(); refreshMissions().then(() => {
  const id = location.hash.slice(1);
  if (id) select(id);
});
setInterval(refreshStatus, 5000);
setInterval(refreshMissions, 3000);
setInterval(refreshMaps, 15000);

// --- the map's scene graph (issue 32) -----------------------------------------------------------------
// Rooms (footprints, names at their centroids), openings and objects of the mission's map, from
// GET /maps/{id}/scene-graph.json, with the mission's trajectory on top. Names follow the planner's text
// form: a type seen once is "kitchen", several are "bedroom 1", "bedroom 2"; an unnamed room is "room N".
let sceneGraph = null;   // { map_id, graph } of the mission on screen
window.sceneGraphProbe = null;  // what the last drawing put on the canvas (for tests and curious users)

function sceneRoomNames(graph) {
  const counts = {}, seen = {}, out = {};
  graph.rooms.forEach((r) => { if (r.room_type) counts[r.room_type] = (counts[r.room_type] || 0) + 1; });
  graph.rooms.forEach((r, k) => {
    if (!r.room_type) { out[r.room_id] = `room ${k + 1}`; return; }
    seen[r.room_type] = (seen[r.room_type] || 0) + 1;
    out[r.room_id] = counts[r.room_type] === 1 ? r.room_type : `${r.room_type} ${seen[r.room_type]}`;
  });
  return out;
}

// The floor a point stands on: the highest floor at most 0.8 m above it (as the planner decides it).
function sceneFloorOf(graph, z) {
  const zs = graph.floors_z_m || [];
  let f = 0;
  zs.forEach((fz, k) => { if (fz <= z + 0.8) f = k; });
  return f;
}

async function loadSceneGraph(mapId) {
  const meta = $("#graph-meta");
  if (!mapId) return;
  if (sceneGraph && sceneGraph.map_id === mapId) { drawSceneGraph(); return; }
  sceneGraph = null;
  meta.textContent = "loading ...";
  try {
    const graph = await api(`/maps/${encodeURIComponent(mapId)}/scene-graph.json`);
    if (!record || record.map_id !== mapId) return;  // another mission was selected meanwhile
    sceneGraph = { map_id: mapId, graph };
    const floors = Math.max(1, (graph.floors_z_m || []).length);
    const select = $("#graph-floor");
    select.replaceChildren(...Array.from({ length: floors }, (_, k) => {
      const o = el("option", "", `floor ${k}`); o.value = String(k); return o;
    }));
    select.value = "";  // follow the robot until the user picks a floor
    select.hidden = floors < 2;
    meta.textContent = `${graph.rooms.length} rooms · ${graph.openings.length} openings · ${graph.objects.length} objects` +
      (graph.labelled ? "" : " · unlabelled map: rooms unnamed");
    drawSceneGraph();
  } catch (e) {
    meta.textContent = `no scene graph (${e.message})`;
    window.sceneGraphProbe = { map_id: mapId, error: e.message, rooms: [] };
    const c = $("#scene-graph");
    c.getContext("2d").clearRect(0, 0, c.width, c.height);
  }
}

function drawSceneGraph() {
  if (!sceneGraph || !record || sceneGraph.map_id !== record.map_id) return;
  const graph = sceneGraph.graph, names = sceneRoomNames(graph);
  const t = record.trajectory || [];
  const picked = $("#graph-floor").value;
  const floor = picked !== "" ? Number(picked) : t.length ? sceneFloorOf(graph, t[t.length - 1][2]) : 0;
  const rooms = graph.rooms.filter((r) => r.floor === floor);
  const ids = new Set(rooms.map((r) => r.room_id));
  const objects = graph.objects.filter((o) => o.room_id ? ids.has(o.room_id) : sceneFloorOf(graph, o.position_m[2] - 0.3) === floor);
  const openings = graph.openings.filter((o) => ids.has(o.a) || ids.has(o.b));
  const path = t.filter((p) => sceneFloorOf(graph, p[2]) === floor);
  // Fit everything drawn, with a margin; +y up as on the spatial map.
  const xs = [], ys = [];
  rooms.forEach((r) => { (r.footprint_m.length ? r.footprint_m : [r.centroid_m]).forEach((p) => { xs.push(p[0]); ys.push(p[1]); }); });
  objects.forEach((o) => { xs.push(o.position_m[0]); ys.push(o.position_m[1]); });
  path.forEach((p) => { xs.push(p[0]); ys.push(p[1]); });
  const c = $("#scene-graph"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const probe = { map_id: sceneGraph.map_id, floor, rooms: [], objects: objects.length, openings: openings.length,
                  trajectory_points: path.length };
  window.sceneGraphProbe = probe;
  if (!xs.length) { g.fillStyle = "#777"; g.font = "16px sans-serif"; g.fillText("nothing mapped on this floor", 20, 30); return; }
  const pad = 30, lo = [Math.min(...xs), Math.min(...ys)], hi = [Math.max(...xs), Math.max(...ys)];
  const s = Math.min((c.width - 2 * pad) / Math.max(hi[0] - lo[0], 1), (c.height - 2 * pad) / Math.max(hi[1] - lo[1], 1));
  const ox = (c.width - s * (hi[0] - lo[0])) / 2, oy = (c.height - s * (hi[1] - lo[1])) / 2;
  const px = (p) => [ox + (p[0] - lo[0]) * s, c.height - oy - (p[1] - lo[1]) * s];
  // Rooms: a pale fill per room (a hue from its index, so neighbours differ), a darker outline.
  rooms.forEach((r, k) => {
    if (r.footprint_m.length < 3) return;
    g.beginPath();
    r.footprint_m.forEach((p, i) => { const [x, y] = px(p); i ? g.lineTo(x, y) : g.moveTo(x, y); });
    g.closePath();
    g.fillStyle = `hsl(${(k * 67) % 360}, 45%, 90%)`; g.fill();
    g.strokeStyle = "#8a8a80"; g.lineWidth = 1.5; g.stroke();
  });
  // Openings: where two rooms meet, an orange bar as wide as the opening.
  g.fillStyle = "#e67e22";
  openings.forEach((o) => {
    const [x, y] = px(o.position_m), w = Math.max(6, (o.width_m || 0.8) * s);
    g.beginPath(); g.arc(x, y, Math.min(7, w / 2), 0, 2 * Math.PI); g.fill();
  });
  // Objects: a dot in their dominant colour.
  objects.forEach((o) => {
    const [x, y] = px(o.position_m), rgb = o.colour_rgb || [0, 0, 0];
    g.beginPath(); g.arc(x, y, 4, 0, 2 * Math.PI);
    g.fillStyle = `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`; g.fill();
    g.strokeStyle = "#222"; g.lineWidth = 1; g.stroke();
  });
  // The trajectory on top of the rooms, under the names.
  if (path.length) {
    g.strokeStyle = "#2f6fde"; g.lineWidth = 3; g.beginPath();
    path.forEach((p, i) => { const [x, y] = px(p); i ? g.lineTo(x, y) : g.moveTo(x, y); });
    g.stroke();
    const [x, y] = px(path[path.length - 1]);
    g.fillStyle = "#ff3b4f"; g.beginPath(); g.arc(x, y, 7, 0, 2 * Math.PI); g.fill();
  }
  // Names last, with a white halo so they read over everything else.
  g.font = "bold 14px system-ui, sans-serif"; g.textAlign = "center"; g.textBaseline = "middle";
  g.lineJoin = "round"; g.lineWidth = 4; g.strokeStyle = "rgba(255,255,255,0.9)"; g.fillStyle = "#1d5e2c";
  rooms.forEach((r) => {
    const name = names[r.room_id], [x, y] = px(r.centroid_m);
    g.strokeText(name, x, y); g.fillText(name, x, y);
    probe.rooms.push({ name, x: Math.round(x), y: Math.round(y) });
  });
}

$("#graph-floor").addEventListener("change", drawSceneGraph);
