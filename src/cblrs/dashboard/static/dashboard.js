// cblrs dashboard: the live map. Reads the site once, then a Server-Sent-Events stream
// (live: /api/stream; replay: /api/replay) and draws on a canvas only when something changed.
// window.cblrsStats exposes what a test or a benchmark reads (draw times from
// performance.now() around each draw, tracks shown, messages, counts).
"use strict";

const HOLD_S = 0.4;      // a mark not in an update for longer than this (capture time) goes
const TRAIL_S = 3.0;     // trail length, capture seconds
const TRAIL_POINTS = 40;
const MAX_EVENTS = 30;
const MAX_ALERTS = 30;
const LABEL_LIMIT = 60;  // ids drawn next to the marks up to this many tracks
const STALE_WALL_S = 3.0; // live: no update for this long (wall clock) and the marks go

const stats = {
  mode: "live", connected: false, messages: 0, tracksMessages: 0, events: 0, draws: 0,
  drawMs: [], lastDrawMs: null, tracksShown: 0, lastT: null, ended: false, live: 0, alerts: 0,
};
window.cblrsStats = stats;

const state = {
  scene: null, view: null, tracks: new Map(), time: null, dirty: true,
  lines: Object.create(null), zones: Object.create(null), cameras: Object.create(null),
  openVisits: Object.create(null), events: [], seenKeys: new Set(),
  alerts: [], activeAlerts: [], seenAlerts: new Set(),
  flashes: Object.create(null), source: null, updates: [],
};
window.cblrsCounts = () => ({
  lines: JSON.parse(JSON.stringify(state.lines)),
  zones: JSON.parse(JSON.stringify(state.zones)),
  cameras: JSON.parse(JSON.stringify(state.cameras)),
});

const $ = (id) => document.getElementById(id);
// Tables keyed by names from the site file or the broker: no prototype, so that a name such
// as "__proto__" is a key like any other.
const dict = () => Object.create(null);

function resetCounts() {
  state.lines = dict();
  state.zones = dict();
  state.openVisits = dict();
  for (const line of state.scene.lines) state.lines[line.name] = { positive: 0, negative: 0 };
  for (const zone of state.scene.zones) {
    state.zones[zone.name] = { now: 0, entries: 0, exits: 0, visits: 0, dwell_s: 0, longest: 0 };
    state.openVisits[zone.name] = new Map();
  }
}

// ------------------------------------------------------------------ messages
function onTracks(message) {
  const t = message.t;
  if (t === null || t === undefined) return;
  const seen = new Set();
  const globals = message.global || [];
  message.rows.forEach(([id, x, y, cls], index) => {
    seen.add(id);
    let track = state.tracks.get(id);
    if (!track) { track = { trail: [], cls }; state.tracks.set(id, track); }
    track.x = x; track.y = y; track.t = t; track.cls = cls || track.cls;
    if (globals[index] !== null && globals[index] !== undefined) track.global = globals[index];
    track.trail.push([x, y, t]);
  });
  // No objects is information too: whoever is not in a newer update goes.
  for (const [id, track] of state.tracks) {
    if (!seen.has(id) && t - track.t > HOLD_S) state.tracks.delete(id);
    else {
      while (track.trail.length && (t - track.trail[0][2] > TRAIL_S
             || track.trail.length > TRAIL_POINTS)) track.trail.shift();
    }
  }
  if (state.time === null || t >= state.time) state.time = t;
  if (!message.tick) {
    CblrsPlaces.heatAdd(message.rows);
    stats.tracksMessages += 1;
    state.updates.push(performance.now());
  }
  state.lastUpdateWall = performance.now();
  stats.lastT = t;
  state.dirty = true;
}

// An alert episode fired or cleared; its "active" list is every episode firing then. Names
// (rules, zones, cameras) come from the site file: shown as text only.
function onAlert(alert) {
  const key = `${alert.episode}\u0000${alert.state}`;
  if (state.seenAlerts.has(key)) return;  // QoS 1, or the retained one again
  state.seenAlerts.add(key);
  stats.alerts += 1;
  if (!alert.recent || !state.alerts.length
      || alert.timestamp >= state.alerts[0].timestamp) {
    state.activeAlerts = Array.isArray(alert.active) ? alert.active : [];
  }
  state.alerts.unshift(alert);
  state.alerts.sort((a, b) => b.timestamp - a.timestamp);
  state.alerts.length = Math.min(state.alerts.length, MAX_ALERTS);
  state.tablesDirty = true;
}

function onEvent(event) {
  if (state.seenKeys.has(event.key)) return;  // QoS 1 may deliver one twice
  state.seenKeys.add(event.key);
  stats.events += 1;
  const replay = stats.mode === "replay";
  if (event.kind === "line_crossed") {
    const line = state.lines[event.place] || (state.lines[event.place] = { positive: 0, negative: 0 });
    // Live: the message's running total is the matcher's count; replay: count here.
    line[event.direction] = replay ? line[event.direction] + 1
      : Math.max(line[event.direction], event.total);
    state.flashes[event.place] = performance.now();
  } else if (event.kind === "zone_entered") {
    const zone = state.zones[event.place];
    if (zone) {
      if (event.crossed) zone.entries += 1;
      (state.openVisits[event.place] ||= new Map()).set(event.track, event.timestamp);
      zone.now = state.openVisits[event.place].size;
    }
  } else if (event.kind === "zone_left") {
    const zone = state.zones[event.place];
    if (zone) {
      zone.visits += 1;
      zone.dwell_s += event.dwell_s;
      if (event.exited) zone.exits += 1;
      (state.openVisits[event.place] ||= new Map()).delete(event.track);
      zone.now = state.openVisits[event.place].size;
    }
  }
  if (!event.recent || state.events.length < MAX_EVENTS) {
    state.events.unshift(event);
    state.events.length = Math.min(state.events.length, MAX_EVENTS);
  }
  state.dirty = true;
  state.tablesDirty = true;
}

function onLive(live) {
  stats.live += 1;
  for (const row of live.lines) state.lines[row.line] = { positive: row.positive, negative: row.negative };
  for (const row of live.zones) {
    const longest = row.dwell.length ? Math.max(...row.dwell.map((item) => item[1])) : 0;
    state.zones[row.zone] = {
      now: row.occupancy, entries: row.entries, exits: row.exits, visits: row.visits,
      dwell_s: row.mean_dwell_s * row.visits, longest,
    };
    state.openVisits[row.zone] = new Map(row.dwell.map(([track, seconds]) =>
      [track, (live.clock || 0) - seconds]));
  }
  for (const camera of live.cameras) {
    state.cameras[camera.camera] = { ...(state.cameras[camera.camera] || {}), ...camera };
  }
  state.dirty = true;
  state.tablesDirty = true;
}

function onCounts(counts) {
  resetCounts();
  for (const [name, row] of Object.entries(counts.lines)) state.lines[name] = { ...row };
  for (const [name, row] of Object.entries(counts.zones)) {
    Object.assign(state.zones[name] || (state.zones[name] = {}), row, { now: 0, longest: 0 });
  }
  for (const [name, visits] of Object.entries(counts.open || {})) {
    state.openVisits[name] = new Map(visits);
    if (state.zones[name]) state.zones[name].now = visits.length;
  }
  state.tablesDirty = true;
}

function onMessage(message) {
  stats.messages += 1;
  switch (message.type) {
    case "tracks": onTracks(message); break;
    case "event": onEvent(message); break;
    case "alert": onAlert(message); break;
    case "live": onLive(message); break;
    case "counts": onCounts(message); break;
    case "status":
      state.cameras[message.camera] = { ...(state.cameras[message.camera] || {}),
        camera: message.camera, online: message.online };
      state.tablesDirty = true;
      break;
    case "hello": stats.mode = message.mode; break;
    case "end":
      stats.ended = true;
      state.tracks.clear();
      state.dirty = true;
      showNotice("replay finished");
      break;
    default: break;
  }
}

// ------------------------------------------------------------------ streams
function connect(url, mode) {
  if (state.source) state.source.close();
  state.tracks.clear();
  state.events = [];
  state.seenKeys.clear();
  state.alerts = [];
  state.activeAlerts = [];
  state.seenAlerts.clear();
  state.time = null;
  state.cameras = dict();
  stats.mode = mode;
  stats.ended = false;
  resetCounts();
  CblrsPlaces.heatReset(state.scene.bounds);
  hideNotice();
  const source = Cblrs.eventStream(url, {
    onopen: () => { stats.connected = true; setConnection(mode, true); },
    onerror: () => {
      stats.connected = false;
      setConnection(mode, false);
      if (mode === "replay" && stats.ended) source.close();
      else Cblrs.checkSession();  // a stream refused or ended because the login did
    },
    onmessage: (message) => onMessage(JSON.parse(message.data)),
  });
  state.source = source;
  $("live-button").classList.toggle("active", mode === "live");
  $("replay-button").classList.toggle("active", mode === "replay");
  state.dirty = true;
  state.tablesDirty = true;
}

function setConnection(mode, ok) {
  const pill = $("connection");
  pill.className = "pill " + (mode === "replay" ? "replay" : ok ? "on" : "off");
  pill.textContent = mode === "replay" ? (ok ? "replay" : "replay ended") : ok ? "live" : "offline";
}

function showNotice(text, info) {
  const n = $("notice");
  n.textContent = text;
  n.classList.toggle("info", Boolean(info));
  n.classList.remove("hidden");
}
function hideNotice() { $("notice").classList.add("hidden"); }

function startReplay() {
  connect(`/api/replay?speed=${$("speed").value}`, "replay");
}

// ------------------------------------------------------------------ drawing
function labels() {
  const lines = dict();
  for (const [name, row] of Object.entries(state.lines)) lines[name] = `+${row.positive} −${row.negative}`;
  const zones = dict();
  for (const [name, row] of Object.entries(state.zones)) {
    zones[name] = { now: row.now, text: `${row.now} now · ${row.entries} entered` };
  }
  return { lines, zones };
}

function draw() {
  const view = state.view;
  const started = performance.now();
  if (view.dirtyStatic) view.drawStatic();
  const ctx = view.canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.drawImage(view.staticLayer, 0, 0);
  ctx.setTransform(view.ratio, 0, 0, view.ratio, 0, 0);
  CblrsPlaces.heatDraw(ctx, view);
  if (CblrsPlaces.editing()) CblrsPlaces.draw(ctx, view);
  else view.drawPlaces(ctx, labels(), state.flashes, started);
  const showTrails = $("trails").checked;
  const count = state.tracks.size;
  ctx.lineWidth = 2;
  ctx.lineJoin = "round";
  for (const [id, track] of state.tracks) {
    const colour = Cblrs.idColour(id);
    if (showTrails && track.trail.length > 1) {
      ctx.strokeStyle = Cblrs.idColour(id, 0.55);
      ctx.beginPath();
      track.trail.forEach(([x, y], index) => {
        const [sx, sy] = view.toScreen(x, y);
        if (index === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
      ctx.stroke();
    }
    const [sx, sy] = view.toScreen(track.x, track.y);
    ctx.fillStyle = colour;
    ctx.beginPath();
    ctx.arc(sx, sy, track.cls && track.cls !== "person" ? 6 : 4.5, 0, 2 * Math.PI);
    ctx.fill();
    if (count <= LABEL_LIMIT) {
      ctx.fillStyle = "#e8edf3";
      ctx.font = "10px system-ui";
      ctx.fillText(Cblrs.trackLabel(id, track.global), sx + 6, sy - 5);
    }
  }
  const elapsed = performance.now() - started;
  stats.draws += 1;
  stats.lastDrawMs = elapsed;
  stats.drawMs.push(elapsed);
  if (stats.drawMs.length > 5000) stats.drawMs.splice(0, stats.drawMs.length - 5000);
  stats.tracksShown = count;
}

function renderTables() {
  const { el, fill } = Cblrs;
  const rows = (id, list) => fill($(id).querySelector("tbody"), list);
  rows("lines", Object.entries(state.lines).map(([name, row]) =>
    el("tr", { dataset: { line: name } }, el("td", {}, name),
      el("td", { className: "positive" }, row.positive),
      el("td", { className: "negative" }, row.negative),
      el("td", {}, row.positive + row.negative))));
  const now = state.time || 0;
  rows("zones", Object.entries(state.zones).map(([name, row]) => {
    let longest = row.longest || 0;
    if (stats.mode === "replay" && state.openVisits[name]) {
      for (const entered of state.openVisits[name].values()) longest = Math.max(longest, now - entered);
    }
    const mean = row.visits ? (row.dwell_s / row.visits).toFixed(1) + " s" : "–";
    return el("tr", { dataset: { zone: name } }, el("td", {}, name),
      el("td", { className: "now" }, row.now), el("td", { className: "entries" }, row.entries),
      el("td", { className: "exits" }, row.exits), el("td", {}, mean),
      el("td", {}, longest ? longest.toFixed(1) + " s" : "–"));
  }));
  const cameras = state.scene.cameras.map((camera) => camera.name);
  for (const name of Object.keys(state.cameras)) if (!cameras.includes(name)) cameras.push(name);
  rows("cameras", cameras.map((name) => {
    const camera = state.cameras[name] || {};
    const dot = camera.online === undefined ? "unknown" : camera.online ? "on" : "off";
    const label = stats.mode === "replay" ? "replay" : camera.online === undefined ? "–"
      : camera.online ? "online" : "offline";
    const age = camera.last_age_s === undefined || camera.last_age_s === null ? "–"
      : camera.last_age_s < 60 ? camera.last_age_s.toFixed(1) + " s" : Math.round(camera.last_age_s / 60) + " min";
    return el("tr", { dataset: { camera: name } }, el("td", {}, name),
      el("td", {}, el("span", { className: `dot ${dot}` }), label),
      el("td", {}, camera.rate_hz === undefined ? "–" : camera.rate_hz.toFixed(1)),
      el("td", {}, age),
      el("td", { className: "rejected" }, camera.rejected === undefined ? "–" : camera.rejected));
  }));
  fill($("alerts-active"), state.activeAlerts.map((alert) =>
    el("li", {}, el("span", {}, `${alert.rule} · ${alert.subject}`),
      el("span", { className: "time" }, `since ${clockText(alert.since)}`))));
  fill($("alerts"), state.alerts.map((alert) =>
    el("li", { className: `state-${alert.state === "fired" ? "fired" : "cleared"}` },
      el("span", { className: "time" }, clockText(alert.timestamp)),
      el("span", {}, alert.state === "fired" ? "fired" : "cleared"),
      el("span", {}, `${alert.rule} · ${alert.subject} · ${Number(alert.value).toFixed(1)}`))));
  fill($("events"), state.events.map((event) => {
    let text = `${event.place} · #${event.track}`;
    if (event.kind === "line_crossed") text += ` · ${event.direction === "positive" ? "+" : "−"}`;
    if (event.kind === "zone_left") text += ` · ${Number(event.dwell_s).toFixed(1)} s`;
    return el("li", { className: `kind-${event.kind}` },
      el("span", { className: "time" }, clockText(event.timestamp)),
      el("span", {}, String(event.kind).replace("_", " ")), el("span", {}, text));
  }));
  state.tablesDirty = false;
}

// Times in the site's time zone (its `timezone:`), labelled with it; UTC without one.
function siteZone() {
  return state.scene ? state.scene.timezone || null : null;
}

function clockText(seconds, withDate = false) {
  return Cblrs.clockText(seconds, siteZone(), withDate);
}

function frame() {
  if (state.dirty) { state.dirty = false; draw(); }
  if (state.tablesDirty) renderTables();
  requestAnimationFrame(frame);
}

setInterval(() => {
  const now = performance.now();
  state.updates = state.updates.filter((time) => now - time < 2000);
  $("stat-tracks").textContent = `${state.tracks.size} tracks`;
  $("stat-rate").textContent = `${(state.updates.length / 2).toFixed(1)} updates/s`;
  $("stat-draw").textContent = stats.lastDrawMs === null ? "–" : stats.lastDrawMs.toFixed(2);
  const hours = state.scene ? state.scene.opening_hours : null;
  $("clock").textContent = clockText(state.time)
    + (state.time > 1e8 ? ` · ${siteZone() || "UTC"}` : "")
    + (hours && state.time > 1e8 && !Cblrs.openAt(state.time, siteZone(), hours) ? " · closed" : "");
  $("clock").title = clockText(state.time, true);
  if (stats.mode === "replay") state.tablesDirty = true;  // live dwell grows
  // A stream that stopped (cameras gone, matcher stopped): nobody is known to be there.
  if (stats.mode === "live" && state.tracks.size && state.lastUpdateWall
      && now - state.lastUpdateWall > STALE_WALL_S * 1000) {
    state.tracks.clear();
    state.dirty = true;
  }
  // Flashing lines fade.
  if (Object.values(state.flashes).some((time) => now - time < 900)) state.dirty = true;
}, 250);

// ------------------------------------------------------------------ start
// The site's places (at start, and again after the places editor saved them).
function applyScene(scene) {
  const counts = { lines: state.lines, zones: state.zones };
  state.scene = scene;
  if (state.view) {
    state.view.scene = scene;
    state.view.resize();
  }
  resetCounts();
  // Counts of places that kept their names stay until the matcher says otherwise.
  for (const name of Object.keys(state.lines)) if (counts.lines[name]) state.lines[name] = counts.lines[name];
  for (const name of Object.keys(state.zones)) if (counts.zones[name]) state.zones[name] = counts.zones[name];
  state.tablesDirty = true;  // the site's lines, zones and cameras, before any message
  state.dirty = true;
  // Which rule made the counts, beside them (rules differ by ~10 % on real tracks).
  const rules = [...new Set(scene.lines.map((line) => line.rule))];
  $("line-rule").textContent = rules.length === 1 ? `counted when: ${rules[0]}`
    : scene.lines.map((line) => `${line.name}: ${line.rule}`).join("; ");
}

const PLANE = Cblrs.planeQuery();  // "?plane=N" on a plane's page of a site's overview

Cblrs.loadSession().then(() => Cblrs.fetchJSON(`/api/site${PLANE}`)).then((scene) => {
  // "/" of a site's overview: the server answers every page by its address alone (never
  // by the session or the site), so the overview's own page is "/?plane=all".
  if (!PLANE && scene.overview) { location.replace("/?plane=all"); return; }
  document.title = `cblrs · ${scene.name}`;
  $("site-name").textContent = `${scene.name} · plane ${scene.plane}`;
  if (scene.overview) $("overview-link").classList.remove("hidden");
  applyScene(scene);
  state.view = new Cblrs.MapView($("map"), scene);
  window.addEventListener("resize", () => { state.view.resize(); state.dirty = true; });
  CblrsPlaces.start({
    view: () => state.view,
    redraw: () => { state.dirty = true; },
    onSaved: () => Cblrs.fetchJSON(`/api/site${PLANE}`).then(applyScene),
    notify: (text) => { showNotice(text, true); setTimeout(hideNotice, 10000); },
    admin: Cblrs.session().role === "admin",
  });
  $("live-button").disabled = !scene.live;
  $("replay-button").disabled = !scene.replay;
  $("live-button").onclick = () => connect(`/api/stream${PLANE}`, "live");
  $("replay-button").onclick = startReplay;
  $("speed").onchange = () => { if (stats.mode === "replay") startReplay(); };
  const wanted = new URLSearchParams(location.search).get("mode");
  if (scene.replay && (wanted === "replay" || !scene.live)) startReplay();
  else if (scene.live) connect(`/api/stream${PLANE}`, "live");
  requestAnimationFrame(frame);
}).catch((error) => showNotice(`cannot load the site: ${error.message}`));
