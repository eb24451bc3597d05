/* Ground station page: plain JavaScript over Leaflet, no build step.
 *
 * Theory of operation
 * -------------------
 * GET /api/config chooses the tile layer (a URL template, the station's offline
 * folder, or none: a plain background) and tells whether this is a replay. The
 * WebSocket /ws pushes {"type":"state"} snapshots (every agent, the leader, recent
 * events) and {"type":"event"}; the page keeps only the newest snapshot and draws
 * it on the next animation frame, so a burst of updates costs one redraw. When the
 * socket drops, the page polls GET /api/state until it reconnects (with back-off).
 * Commands go over the socket ({"type":"command","id":N,...}, answered by a
 * "command_result" with the same id) or, while it is down, POST /api/command; every
 * answer, and every refusal with its reason, lands in the event log.
 *
 * Token (a station beyond loopback, or started with --token): the operator opens
 * /?token=...; the station answers with the page and an HttpOnly cookie that every
 * later request and the socket carry. The page drops the token from the address
 * bar at once (history.replaceState), so it is not in the history, a bookmark or a
 * copied link. A 401 (a restarted station with a new token) lands in the log.
 *
 * Stable hooks for tests: #agents [data-agent-id], .agent-marker[data-agent-id],
 * #telemetry [data-field], #election [data-field], #log, #cmd-status, window.gcs.
 */
(function () {
  "use strict";

  const COMMAND_TIMEOUT_MS = 20000;
  const POLL_MS = 1000;
  const LOG_MAX = 300;
  const TRAIL_POINTS = 40;  // a short trail: the newest points the station sends
  const ARROW = '<svg class="arrow" viewBox="-16 -16 32 32" aria-hidden="true">' +
    '<path d="M0,-13 L9,11 L0,6 L-9,11 Z"/></svg><span class="tag"></span>';

  const $ = (sel) => document.querySelector(sel);
  const S = {
    config: null,
    map: null,
    trailRenderer: null,
    state: null,          // newest snapshot
    drawn: null,          // snapshot last drawn
    renderQueued: false,
    renderMs: [],         // how long drawing each snapshot took (for the benchmark)
    stateCount: 0,
    lastStateTime: null,  // station time of the newest snapshot
    lastStateAt: 0,       // performance.now() when it arrived
    agents: new Map(),    // id -> {data, marker, el, arrow, tag, trail, row}
    selected: null,
    fitted: false,
    ws: null,
    wsStatus: "connecting",
    backoff: 500,
    pollTimer: null,
    seq: 0,
    pending: new Map(),   // command id -> {cmd, resolve, timer}
    awaiting: null,       // {kind, what}: a command shown in progress, its result still to come
    seenEvents: new Set(),
    target: null,         // the go-to target marker
    altTyped: false,      // the operator typed a go-to altitude
    replay: null,
    replayAt: -Infinity,  // when the socket last pushed the replay status
    tokenWarned: false,
  };

  // the station has set the URL's token as a cookie: keep it out of the address bar
  (function dropToken() {
    const u = new URL(location.href);
    if (!u.searchParams.has("token")) return;
    u.searchParams.delete("token");
    history.replaceState(history.state, "", u.pathname + u.search + u.hash);
  })();

  function tokenRefused(what) {
    if (S.tokenWarned) return;
    S.tokenWarned = true;
    log("error", what + ": the station wants its token: open the address it printed (…/?token=…)", "error");
  }

  // ---------------------------------------------------------------- helpers
  function fmt(v, digits, unit) {
    if (v === null || v === undefined || Number.isNaN(v)) return "—";
    return Number(v).toFixed(digits) + (unit ? " " + unit : "");
  }
  function agentName(id) {
    const a = S.agents.get(id);
    return a ? a.data.name + " (" + id + ")" : "agent " + id;
  }
  function hasPosition(a) {
    return typeof a.lat === "number" && typeof a.lon === "number" && !(a.lat === 0 && a.lon === 0);
  }
  function setText(el, text) {
    if (el && el.textContent !== text) el.textContent = text;
  }
  function clock(t) {
    if (typeof t !== "number") return new Date().toLocaleTimeString();
    if (t > 1e9) return new Date(t * 1000).toLocaleTimeString();
    return "+" + t.toFixed(1) + " s";
  }

  // ---------------------------------------------------------------- event log
  function log(kind, text, cls, t) {
    const li = document.createElement("li");
    li.dataset.kind = kind;
    if (cls) li.className = cls;
    const ts = document.createElement("span");
    ts.className = "t";
    ts.textContent = clock(t);
    const k = document.createElement("span");
    k.className = "kind";
    k.textContent = kind;
    const msg = document.createElement("span");
    msg.className = "text";
    msg.textContent = text;
    li.append(ts, k, msg);
    const ol = $("#log");
    ol.prepend(li);
    while (ol.children.length > LOG_MAX) ol.lastElementChild.remove();
  }
  function stationEvent(e) {
    if (!e || typeof e !== "object") return;
    const key = e.t + "|" + e.kind + "|" + e.text;
    if (S.seenEvents.has(key)) return;
    S.seenEvents.add(key);
    if (S.seenEvents.size > 2000) S.seenEvents = new Set(Array.from(S.seenEvents).slice(-1000));
    const kind = String(e.kind || "event");
    const text = String(e.text || "");
    const bad = /refus|reject|fail|denied|timeout|error|lost|disconnect|no_answer/i.test(kind + " " + text);
    log(kind, text, bad ? "refused" : "", e.t);
    // the result of a command the page showed as in progress (its vehicle was still at it)
    const m = kind === "command" && S.awaiting ? /^([A-Z_]+) -> [^:]*: ([A-Z_]+)/.exec(text) : null;
    if (m && m[1] === S.awaiting.kind && m[2] !== "IN_PROGRESS") {
      const result = text.slice(text.indexOf(": ") + 2).replace(/ \[seq \d+\]$/, "");
      if (m[2] === "ACCEPTED") status(S.awaiting.what + ": accepted", true);
      else if (m[2] === "CARRIED_OUT") status(S.awaiting.what + ": carried out: " + result, true);
      else status(S.awaiting.what + ": refused: " + result, false);
      S.awaiting = null;
    }
  }
  function status(text, ok, cls) {
    const el = $("#cmd-status");
    el.hidden = false;
    el.textContent = text;
    el.className = "status " + (cls || (ok ? "ok" : "refused"));
  }

  // ---------------------------------------------------------------- map
  function initMap(cfg) {
    const map = L.map("map", { zoomControl: true, attributionControl: true, worldCopyJump: true });
    S.map = map;
    S.trailRenderer = L.canvas({ padding: 0.3 });
    if (cfg.tiles) {
      L.tileLayer(cfg.tiles, {
        maxZoom: 21, maxNativeZoom: 19, attribution: cfg.attribution || "",
        errorTileUrl: "data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw==",
      }).addTo(map);
    } else {
      $("#map").classList.add("no-tiles");
      map.attributionControl.addAttribution("no map tiles");
    }
    L.control.scale({ imperial: false }).addTo(map);
    if (Array.isArray(cfg.center) && cfg.center.length === 2) {
      map.setView(cfg.center, 17);
    } else {
      map.setView([0, 0], 2);
    }
    map.on("click", (ev) => setGotoTarget(ev.latlng.lat, ev.latlng.lng));
  }

  function setGotoTarget(lat, lon) {
    $("#goto-lat").value = lat.toFixed(7);
    $("#goto-lon").value = lon.toFixed(7);
    placeTarget(lat, lon);
  }
  function placeTarget(lat, lon) {
    if (!S.map || !Number.isFinite(lat) || !Number.isFinite(lon)) return;
    if (!S.target) {
      S.target = L.marker([lat, lon], {
        icon: L.divIcon({ className: "goto-target", html: "✕", iconSize: [22, 22], iconAnchor: [11, 11] }),
        interactive: false, keyboard: false,
      }).addTo(S.map);
      S.target.getElement().id = "goto-target";
    } else {
      S.target.setLatLng([lat, lon]);
    }
  }

  function makeAgent(a) {
    const rec = { data: a, marker: null, el: null, arrow: null, tag: null, trail: null, row: null, view: {} };
    const li = document.createElement("li");
    li.dataset.agentId = String(a.id);
    li.innerHTML = '<span class="dot"></span><span class="name"></span><span class="lead" hidden>L</span>' +
      '<span class="badge"></span>';
    li.tabIndex = 0;
    li.addEventListener("click", () => select(a.id, true));
    li.addEventListener("keydown", (ev) => {
      if (ev.key === "Enter" || ev.key === " ") {
        ev.preventDefault();
        select(a.id, true);
      }
    });
    rec.row = li;
    rec.rowName = li.querySelector(".name");
    rec.rowLead = li.querySelector(".lead");
    rec.rowBadge = li.querySelector(".badge");
    S.agents.set(a.id, rec);
    return rec;
  }
  function ensureMarker(rec) {
    if (rec.marker || !S.map) return;
    const a = rec.data;
    rec.trail = L.polyline([], {
      renderer: S.trailRenderer, color: "#2b8cff", weight: 2, opacity: 0.7, interactive: false,
    }).addTo(S.map);
    rec.marker = L.marker([a.lat, a.lon], {
      icon: L.divIcon({ className: "agent-marker", html: ARROW, iconSize: [32, 32], iconAnchor: [16, 16] }),
      keyboard: false, riseOnHover: true, title: a.name,
    }).addTo(S.map);
    rec.marker.on("click", () => select(a.id, false));
    rec.el = rec.marker.getElement();
    rec.el.dataset.agentId = String(a.id);
    rec.arrow = rec.el.querySelector(".arrow");
    rec.tag = rec.el.querySelector(".tag");
    rec.view = {};  // draw everything on the new marker
  }
  function dropAgent(id) {
    const rec = S.agents.get(id);
    if (!rec) return;
    if (rec.marker) rec.marker.remove();
    if (rec.trail) rec.trail.remove();
    rec.row.remove();
    S.agents.delete(id);
    if (S.selected === id) select(null, false);
  }

  // ---------------------------------------------------------------- drawing
  function onState(msg) {
    S.state = msg;
    S.stateCount += 1;
    S.lastStateTime = msg.time;
    S.lastStateAt = performance.now();
    // a delta without new events keeps the same list: nothing to look through
    if (Array.isArray(msg.events) && msg.events !== S.eventsSeen) msg.events.forEach(stationEvent);
    S.eventsSeen = msg.events;
    if (!S.renderQueued) {
      S.renderQueued = true;
      requestAnimationFrame(render);
    }
  }

  function render() {
    S.renderQueued = false;
    const st = S.state;
    if (!st || st === S.drawn) return;
    const t0 = performance.now();
    drawState(st);
    S.renderMs.push(performance.now() - t0);
    if (S.renderMs.length > 1000) S.renderMs.splice(0, S.renderMs.length - 500);
  }

  function drawState(st) {
    S.drawn = st;
    const agents = Array.isArray(st.agents) ? st.agents : [];
    const leader = st.leader || 0;
    const seen = new Set();
    const list = $("#agents");
    const empty = list.querySelector(".empty");
    if (agents.length && empty) empty.remove();
    for (const a of agents) {
      const id = a.id;
      seen.add(id);
      let rec = S.agents.get(id);
      if (!rec) {
        rec = makeAgent(a);
        list.append(rec.row);
      }
      rec.data = a;
      drawAgent(rec, id === leader);
    }
    for (const id of Array.from(S.agents.keys())) if (!seen.has(id)) dropAgent(id);
    if (!agents.length && !list.children.length) {
      list.innerHTML = '<li class="empty">no agent yet</li>';
    }
    if (!S.fitted) fitToAgents();
    drawHeader(st, agents, leader);
    drawElection(agents, leader);
    drawTelemetry();
  }

  // Each agent's last drawn values: only what changed touches the DOM or the map
  // (50 agents at 2-5 snapshots a second stay well inside a frame).
  function drawAgent(rec, isLeader) {
    const a = rec.data;
    const off = !a.connected;
    const selected = S.selected === a.id;
    const v = rec.view;
    // a delta leaves an unchanged agent's object as it was: nothing to draw
    if (v.src === a && v.leader === isLeader && v.selected === selected && (rec.marker || !hasPosition(a))) return;
    v.src = a;
    if (hasPosition(a)) {
      ensureMarker(rec);
      if (a.lat !== v.lat || a.lon !== v.lon) {
        rec.marker.setLatLng([a.lat, a.lon]);
        v.lat = a.lat;
        v.lon = a.lon;
      }
      const h = (Number(a.heading) || 0).toFixed(1);
      if (h !== v.heading) {
        rec.arrow.style.transform = "rotate(" + h + "deg)";
        rec.el.dataset.heading = h;
        v.heading = h;
      }
      if (isLeader !== v.leader || off !== v.off || selected !== v.selected || a.name !== v.name) {
        setText(rec.tag, (isLeader ? "L " : "") + a.name);
        rec.el.classList.toggle("leader", isLeader);
        rec.el.classList.toggle("disconnected", off);
        rec.el.classList.toggle("selected", selected);
        rec.el.dataset.leader = isLeader ? "1" : "0";
        rec.el.dataset.connected = off ? "0" : "1";
        rec.marker.setZIndexOffset(isLeader ? 500 : 0);
        rec.trail.setStyle({ color: off ? "#7d858c" : (isLeader ? "#ffb400" : "#2b8cff") });
      }
      const trail = Array.isArray(a.trail) ? a.trail.slice(-TRAIL_POINTS) : [];
      const last = trail.length ? trail[trail.length - 1] : null;
      const key = trail.length + (last ? ":" + last[0] + "," + last[1] + ":" + trail[0][0] + "," + trail[0][1] : "");
      if (key !== v.trail) {
        rec.trail.setLatLngs(trail);
        v.trail = key;
      }
    }
    if (isLeader !== v.leader || off !== v.off || selected !== v.selected || a.name !== v.name) {
      const row = rec.row;
      row.classList.toggle("disconnected", off);
      row.classList.toggle("leader", isLeader);
      row.classList.toggle("selected", selected);
      row.dataset.connected = off ? "0" : "1";
      setText(rec.rowName, a.name + " (" + a.id + ")");
      rec.rowLead.hidden = !isLeader;
    }
    // a flight controller gone silent is said in the agent's entry, not just in the log
    setText(rec.rowBadge, off ? "disconnected" : a.vehicle_link === false ? "vehicle link lost"
      : String(a.phase || "").toLowerCase());
    v.leader = isLeader;
    v.off = off;
    v.selected = selected;
    v.name = a.name;
  }


  function fitToAgents() {
    const pts = [];
    for (const rec of S.agents.values()) if (hasPosition(rec.data)) pts.push([rec.data.lat, rec.data.lon]);
    if (!pts.length || !S.map) return;
    S.fitted = true;
    if (pts.length === 1) S.map.setView(pts[0], 18);
    else S.map.fitBounds(pts, { padding: [60, 60], maxZoom: 18 });
  }

  function drawHeader(st, agents, leader) {
    if (st.station) {
      const s = st.station;
      setText($("#station"), (s.name || "station") + " #" + (s.id ?? "?") + (s.link ? " · " + s.link : ""));
    }
    setText($("#leader-summary"), "leader: " + (leader ? agentName(leader) : "none"));
    const up = agents.filter((a) => a.connected).length;
    setText($("#agent-count"), up + "/" + agents.length + " agents connected");
  }

  function drawElection(agents, leader) {
    const el = $("#election");
    setText(el.querySelector('[data-field="leader"]'), leader ? agentName(leader) : "none");
    const phases = {};
    for (const a of agents) if (a.connected) phases[a.phase || "?"] = (phases[a.phase || "?"] || 0) + 1;
    setText(el.querySelector('[data-field="phases"]'),
      Object.keys(phases).sort().map((p) => p + " " + phases[p]).join(", ") || "—");
    const ref = S.agents.get(leader) || S.agents.get(S.selected);
    const d = ref ? ref.data : null;
    const ids = (v) => (Array.isArray(v) && v.length ? v.join(", ") : "—");
    setText(el.querySelector('[data-field="pool"]'), d ? ids(d.pool) + (d.locked ? " (locked)" : "") : "—");
    setText(el.querySelector('[data-field="members"]'), d ? ids(d.members) : "—");
  }

  function drawTelemetry() {
    const el = $("#telemetry");
    const rec = S.selected !== null ? S.agents.get(S.selected) : null;
    el.dataset.agentId = rec ? String(S.selected) : "";
    const f = (name, text) => setText(el.querySelector('[data-field="' + name + '"]'), text);
    if (!rec) {
      setText($("#telemetry-title"), "(select an agent)");
      for (const dd of el.querySelectorAll("dd")) setText(dd, "—");
      return;
    }
    const a = rec.data;
    setText($("#telemetry-title"), a.name + " (" + a.id + ")" + (a.connected ? "" : " — disconnected"));
    f("mode", a.vehicle_link === false ? "unknown (vehicle link lost)" : a.mode || "—");
    f("armed", a.armed ? "armed" : "disarmed");
    f("alt", fmt(a.alt, 1, "m") + (a.airborne ? " (airborne)" : ""));
    f("groundspeed", fmt(a.groundspeed, 1, "m/s"));
    f("heading", fmt(a.heading, 0, "°"));
    f("battery", a.battery === null || a.battery === undefined ? "unknown" : fmt(a.battery, 0, "%"));
    f("rssi", (a.rssi ?? "—") + " / " + (a.remrssi ?? "—"));
    f("last_seen", fmt(a.last_seen_s, 1, "s ago"));
    f("position", hasPosition(a) ? a.lat.toFixed(6) + ", " + a.lon.toFixed(6) : "—");
    f("state", String(a.phase || "—") + (a.leader ? ", leader " + a.leader : "") + (a.holding ? ", holding" : ""));
  }

  function select(id, pan) {
    S.selected = id;
    for (const [aid, rec] of S.agents) {
      rec.row.classList.toggle("selected", aid === id);
      if (rec.el) rec.el.classList.toggle("selected", aid === id);
    }
    const rec = id !== null ? S.agents.get(id) : null;
    if (rec && pan && rec.marker && S.map) S.map.panTo(rec.marker.getLatLng());
    // the go-to altitude (AMSL) follows the selected agent until the operator types one:
    // its own altitude when flying, 10 m above it on the ground
    if (rec && !S.altTyped && typeof rec.data.alt === "number") {
      $("#goto-alt").value = String(Math.round(rec.data.alt + (rec.data.airborne ? 0 : 10)));
    }
    drawTelemetry();
    if (S.drawn) drawElection(S.drawn.agents || [], S.drawn.leader || 0);
  }

  // ---------------------------------------------------------------- live link
  function setLink(status) {
    S.wsStatus = status;
    const el = $("#link-status");
    el.dataset.status = status;
    el.textContent = status;
  }

  function connect() {
    const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
    let ws;
    try {
      ws = new WebSocket(url);
    } catch (err) {
      scheduleReconnect();
      return;
    }
    S.ws = ws;
    ws.onopen = () => {
      S.model = null;  // the station sends the whole state first
      S.resyncAsked = false;
      S.backoff = 500;
      setLink("live");
      stopPolling();
    };
    ws.onmessage = (ev) => {
      let msg;
      try {
        msg = JSON.parse(ev.data);
      } catch (err) {
        return;
      }
      onMessage(msg);
    };
    ws.onclose = () => {
      if (S.ws !== ws) return;
      S.ws = null;
      // commands in flight over this socket get no answer any more
      for (const [id, p] of S.pending) {
        clearTimeout(p.timer);
        S.pending.delete(id);
        p.resolve({ status: 0, error: "connection to the station lost before the answer" });
      }
      scheduleReconnect();
    };
    ws.onerror = () => {};
  }
  function scheduleReconnect() {
    setLink("reconnecting");
    startPolling();
    setTimeout(connect, S.backoff);
    S.backoff = Math.min(S.backoff * 2, 5000);
  }
  function startPolling() {
    if (S.pollTimer) return;
    const poll = async () => {
      try {
        const r = await fetch("/api/state", { cache: "no-store" });
        if (r.ok) onState(await r.json());
        else if (r.status === 401) tokenRefused("GET /api/state");
      } catch (err) { /* station unreachable: keep trying */ }
    };
    poll();
    S.pollTimer = setInterval(poll, POLL_MS);
  }
  function stopPolling() {
    if (S.pollTimer) clearInterval(S.pollTimer);
    S.pollTimer = null;
  }

  function onMessage(msg) {
    switch (msg.type) {
      case "state":  // the whole state: deltas follow from its seq
        S.model = msg;
        S.resyncAsked = false;
        onState(msg);
        break;
      case "delta": {  // what changed since the state the page holds (delta.js)
        const st = window.gcsDelta.next(S.model, S.model ? S.model.seq : null, msg);
        if (st) {
          S.model = st;
          onState(st);
        } else if (!S.resyncAsked && S.ws && S.ws.readyState === WebSocket.OPEN) {
          S.resyncAsked = true;  // a gap, or no state yet: ask for the whole state
          S.ws.send('{"type":"state"}');
        }
        break;
      }
      case "event":
        stationEvent(msg.event);
        break;
      case "replay":  // replay mode: the status follows each state push
        S.replayAt = performance.now();
        drawReplay(msg);
        break;
      case "command_result": {
        const p = S.pending.get(msg.id);
        if (p) {
          clearTimeout(p.timer);
          S.pending.delete(msg.id);
          p.resolve(msg);
        }
        break;
      }
      case "error": {
        const p = msg.id !== undefined ? S.pending.get(msg.id) : null;
        if (p) {
          clearTimeout(p.timer);
          S.pending.delete(msg.id);
          p.resolve({ status: msg.status || 400, error: msg.reason || "error" });
        } else {
          log("error", "station: " + (msg.reason || "error") + (msg.status ? " (" + msg.status + ")" : ""), "error");
        }
        break;
      }
      default:
        break;
    }
  }

  // ---------------------------------------------------------------- commands
  function sendCommand(cmd) {
    if (S.ws && S.ws.readyState === WebSocket.OPEN) {
      return new Promise((resolve) => {
        const id = ++S.seq;
        const timer = setTimeout(() => {
          S.pending.delete(id);
          resolve({ status: 0, error: "no answer from the station in " + COMMAND_TIMEOUT_MS / 1000 + " s" });
        }, COMMAND_TIMEOUT_MS);
        S.pending.set(id, { cmd, resolve, timer });
        S.ws.send(JSON.stringify(Object.assign({ type: "command", id }, cmd)));
      });
    }
    return fetch("/api/command", {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(cmd),
    }).then(async (r) => {
      let body = {};
      try {
        body = await r.json();
      } catch (err) { /* not JSON */ }
      return Object.assign({ status: r.status }, body);
    }, (err) => ({ status: 0, error: "station unreachable: " + err }));
  }

  function describe(cmd) {
    const who = cmd.target === "swarm" ? "swarm" : agentName(cmd.target);
    let what = cmd.kind;
    if (cmd.kind === "goto" || cmd.kind === "waypoint") what += " " + cmd.lat.toFixed(6) + ", " + cmd.lon.toFixed(6) + " alt " + cmd.alt + " m";
    if (cmd.kind === "takeoff") what += " to " + cmd.alt + " m";
    if (cmd.kind === "follow") what += " heading " + cmd.heading + "°";
    return what + " → " + who;
  }

  function report(cmd, r) {
    const what = describe(cmd);
    const err = r.error || (r.status >= 400 ? r.reason || "refused (" + r.status + ")" : null);
    if (err) {
      log("refused", what + ": " + err, "refused");
      status(what + ": refused: " + err, false);
      return;
    }
    const results = Array.isArray(r.results) ? r.results : [];
    const bad = [];
    const busy = [];
    for (const x of results) {
      const res = String(x.result || "");
      // CARRIED_OUT: no answer, but the agent's telemetry shows it done (the reason says how)
      const good = /^(ok|accepted|done|sent|success|carried_out)$/i.test(res);
      // IN_PROGRESS: the vehicle is still at it (a take-off climbing): not done, not refused
      if (/^in_progress$/i.test(res)) {
        busy.push(agentName(x.agent) + (x.reason ? ": " + x.reason : ""));
        continue;
      }
      // the station logs every answer as an event; the page adds the refusals in red
      if (!good) {
        log("refused", what + ": " + agentName(x.agent) + " " + res + (x.reason ? ": " + x.reason : ""), "refused");
        bad.push(agentName(x.agent) + " " + res + (x.reason ? ": " + x.reason : ""));
      }
    }
    if (!results.length && r.ok === false) log("refused", what + ": not done", "refused");
    if (bad.length) status(what + ": refused: " + bad.join("; "), false);
    else if (busy.length) {
      S.awaiting = { kind: String(cmd.kind).toUpperCase(), what };
      status(what + ": in progress: " + busy.join("; ") + " (the result follows in the log)", false, "pending");
    } else if (r.ok === false) status(what + ": not done", false);
    else if (results.some((x) => x.result === "CARRIED_OUT")) status(what + ": carried out (no answer; the telemetry shows it)", true);
    else status(what + ": accepted", true);
  }

  async function command(cmd) {
    status(describe(cmd) + ": sending…", true);
    const r = await sendCommand(cmd);
    report(cmd, r);
    return r;
  }

  function localRefusal(text) {
    log("refused", text, "refused");
    status(text, false);
  }

  function initControls() {
    $("#goto").addEventListener("submit", (ev) => {
      ev.preventDefault();
      // Go replaces the agent's route; + Waypoint appends to it
      const kind = ev.submitter && ev.submitter.id === "goto-waypoint" ? "waypoint" : "goto";
      if (S.selected === null) return localRefusal(kind + ": select an agent first");
      const lat = parseFloat($("#goto-lat").value);
      const lon = parseFloat($("#goto-lon").value);
      const alt = parseFloat($("#goto-alt").value);
      if (![lat, lon, alt].every(Number.isFinite) || Math.abs(lat) > 90 || Math.abs(lon) > 180) {
        return localRefusal(kind + ": latitude, longitude and altitude must be numbers");
      }
      placeTarget(lat, lon);
      command({ target: S.selected, kind, lat, lon, alt });
    });
    $("#fit-swarm").addEventListener("click", fitToAgents);
    $("#goto-alt").addEventListener("input", () => { S.altTyped = true; });
    for (const input of [$("#goto-lat"), $("#goto-lon")]) {
      input.addEventListener("change", () => {
        const lat = parseFloat($("#goto-lat").value);
        const lon = parseFloat($("#goto-lon").value);
        if (Number.isFinite(lat) && Number.isFinite(lon)) placeTarget(lat, lon);
      });
    }
    for (const btn of document.querySelectorAll("#commands button[data-kind]")) {
      btn.addEventListener("click", () => {
        const kind = btn.dataset.kind;
        let target = "swarm";
        if ($("#cmd-target").value === "selected") {
          if (S.selected === null) return localRefusal(kind + ": select an agent first");
          target = S.selected;
        }
        const cmd = { target, kind };
        if (kind === "takeoff") {
          cmd.alt = parseFloat($("#takeoff-alt").value);
          if (!Number.isFinite(cmd.alt)) return localRefusal("take off: altitude must be a number");
        }
        if (kind === "follow") {
          cmd.heading = parseFloat($("#follow-heading").value);
          if (!Number.isFinite(cmd.heading)) return localRefusal("follow: heading must be a number");
        }
        command(cmd);
      });
    }
  }

  // ---------------------------------------------------------------- replay
  function mmss(s) {
    s = Math.max(0, Math.round(Number(s) || 0));
    return Math.floor(s / 60) + ":" + String(s % 60).padStart(2, "0");
  }
  function drawReplay(r) {
    if (!r || typeof r !== "object") return;
    S.replay = r;
    $("#replay-play").innerHTML = r.playing ? "&#10074;&#10074;" : "&#9654;";
    $("#replay-play").dataset.playing = r.playing ? "1" : "0";
    const seek = $("#replay-seek");
    seek.max = String(r.duration_s || 0);
    if (document.activeElement !== seek) seek.value = String(r.position_s || 0);
    const sp = $("#replay-speed");
    if (document.activeElement !== sp && r.speed !== undefined) {
      const v = String(r.speed);
      if (!Array.from(sp.options).some((o) => o.value === v)) sp.add(new Option(v + "×", v));
      sp.value = v;
    }
    setText($("#replay-time"), mmss(r.position_s) + " / " + mmss(r.duration_s));
  }
  async function replayAction(action, value) {
    try {
      const body = value === undefined ? { action } : { action, value };
      const r = await fetch("/api/replay", {
        method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
      });
      const data = await r.json();
      if (!r.ok) log("refused", "replay " + action + ": " + (data.error || r.status), "refused");
      else drawReplay(data);
    } catch (err) {
      log("error", "replay " + action + ": " + err, "error");
    }
  }
  function initReplay() {
    $("#replay").hidden = false;
    document.body.classList.add("replay");
    // a capture plays: nothing to command
    for (const el of document.querySelectorAll("#commands button, #goto button")) {
      el.disabled = true;
      el.title = "replay: commands are disabled while a capture plays";
    }
    $("#replay-play").addEventListener("click", () => replayAction(S.replay && S.replay.playing ? "pause" : "play"));
    $("#replay-speed").addEventListener("change", (ev) => replayAction("speed", parseFloat(ev.target.value)));
    $("#replay-seek").addEventListener("change", (ev) => replayAction("seek", parseFloat(ev.target.value)));
    const poll = async () => {
      if (performance.now() - S.replayAt < 2 * POLL_MS) return;  // pushed over the socket
      try {
        const r = await fetch("/api/replay", { cache: "no-store" });
        if (r.ok) drawReplay(await r.json());
      } catch (err) { /* keep trying */ }
    };
    poll();
    setInterval(poll, POLL_MS);
  }

  // ---------------------------------------------------------------- frame probe
  // requestAnimationFrame deltas, for the page benchmark (off unless started)
  const probe = { running: false, last: 0, deltas: [] };
  function probeTick(ts) {
    if (!probe.running) return;
    if (probe.last) probe.deltas.push(ts - probe.last);
    probe.last = ts;
    requestAnimationFrame(probeTick);
  }

  window.gcs = Object.freeze({
    get ready() { return S.map !== null; },
    get config() { return S.config; },
    get markers() { let n = 0; for (const r of S.agents.values()) if (r.marker) n += 1; return n; },
    get agents() { return Array.from(S.agents.keys()); },
    get selected() { return S.selected; },
    get leader() { return S.drawn ? S.drawn.leader || 0 : 0; },
    get stateCount() { return S.stateCount; },
    get lastStateTime() { return S.lastStateTime; },
    get wsStatus() { return S.wsStatus; },
    markerLatLng(id) {
      const r = S.agents.get(id);
      if (!r || !r.marker) return null;
      const ll = r.marker.getLatLng();
      return [ll.lat, ll.lng];
    },
    renderTimes() { return S.renderMs.slice(); },
    frameProbe: Object.freeze({
      start() { S.renderMs = []; probe.deltas = []; probe.last = 0; if (!probe.running) { probe.running = true; requestAnimationFrame(probeTick); } },
      stop() { probe.running = false; return probe.deltas.slice(); },
    }),
  });

  // ---------------------------------------------------------------- start
  async function start() {
    let cfg = { tiles: null, attribution: "", station: null, replay: false, center: null };
    try {
      const r = await fetch("/api/config", { cache: "no-store" });
      if (r.ok) cfg = Object.assign(cfg, await r.json());
      else if (r.status === 401) tokenRefused("GET /api/config");
      else log("error", "GET /api/config: " + r.status, "error");
    } catch (err) {
      log("error", "GET /api/config failed: " + err, "error");
    }
    S.config = cfg;
    if (cfg.station) setText($("#station"), (cfg.station.name || "station") + " #" + (cfg.station.id ?? "?"));
    initMap(cfg);
    initControls();
    if (cfg.replay) initReplay();
    select(null, false);
    connect();
  }
  start();
})();
