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
 * Token (a station beyond loopback, or started with --token): token.js keeps it
 * (from the printed /?token=... address, out of the address bar at once) in the
 * page's own origin's storage; every request here goes through gcsToken.fetch (the
 * token as "Authorization: Bearer"), the socket offers it as a subprotocol, and the
 * station's own tiles are fetched with it. A 401 (no token, or a restarted station
 * with a new one) lands in the log and shows the form asking for it.
 *
 * Fleet table (#agents): one row per agent, its colour (a fixed palette by id: the
 * same on the marker, the trail and the row; the leader keeps its colour and is
 * marked with a gold outline and "L"), sortable by a header click, a row click
 * selects. Honest state: a timer ages the newest snapshot ("updated 0.4 s ago");
 * once the socket has closed with no fresher data, or nothing came for 2.5 push
 * periods (or polls; at least 1 s), the page greys the map and the table and says
 * "station lost" in a banner; an agent the station reports disconnected, or not
 * heard for AGENT_STALE_S (or 3 of its heartbeats, hb_s), shows its last values
 * greyed with their age.
 * Commands: the target is the selected agent unless the operator picks "whole
 * swarm" (reset after each swarm command); every swarm command and every land,
 * return, disarm and take-off asks first in a dialog naming the command and its
 * addressees; "Hold all" (the swarm STOP: every connected agent holds where it is)
 * is one click.
 *
 * Several swarms (swarms.js, window.gcsSwarms): each agent's colour is its swarm's,
 * every swarm's leader is marked, the table sorts by swarm by default (by id with one
 * swarm), and the "to" selector may hold "swarm:<leader id>"; window.gcsDrawHooks are
 * called after each drawn state.
 *
 * Stable hooks for tests: #agents [data-agent-id] (rows, .lead, .stale,
 * [data-field]), .agent-marker[data-agent-id][data-colour], #telemetry [data-field],
 * #election [data-field], #log, #cmd-status, #stale-banner, #confirm, #hold-all, #take-back [data-take],
 * window.gcs.
 */
(function () {
  "use strict";

  const COMMAND_TIMEOUT_MS = 20000;
  const POLL_MS = 1000;
  const LOG_MAX = 300;
  const TRAIL_POINTS = 40;  // a short trail: the newest points the station sends
  const STALE_MIN_MS = 1000;  // no state for 2.5 push periods, and at least this long: the station is lost
  const AGENT_STALE_S = 3;  // an agent not heard for this long (or 3 of its heartbeats): its values are stale
  // one colour per agent by id: no red (alerts), yellow (the leader's mark) or grey (stale)
  const PALETTE = ["#4e9bff", "#3fd0c9", "#c17dff", "#ff7fc4", "#6fd35a", "#ff9a3c",
    "#8fa8ff", "#2fe3a0", "#e37bff", "#54c6ff", "#b6e05a", "#d9a6ff"];
  const OFF_COLOUR = "#7d858c";
  // commands asked about first (and every command to the whole swarm)
  const CONFIRM_KINDS = new Set(["land", "return", "disarm", "takeoff"]);
  const VERBS = { arm: "Arm", disarm: "Disarm", takeoff: "Take off", land: "Land", return: "Return",
    follow: "Follow in V", stop: "Hold", goto: "Go", waypoint: "Add a waypoint" };
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
    follow: null,         // {request, what, note, agents}: a command the agents took, followed on their vehicles
    followEnded: null,    // the "what" of the last follow-up that ended (its outcome is the last word)
    seenEvents: new Set(),
    target: null,         // the go-to target marker
    altTyped: false,      // the operator typed a go-to altitude
    replay: null,
    replayAt: -Infinity,  // when the socket last pushed the replay status
    tokenWarned: false,
    lostAt: -Infinity,    // performance.now() when the socket last went away
    stale: false,         // the page's data is too old to trust
    sort: { key: "swarm", dir: 1 },  // by swarm when several (swarms.js), else by id
    order: "",            // the fleet table's row order last drawn
    confirming: false,    // the confirmation dialog is open
  };

  const api = window.gcsToken.fetch;  // fetch with the station's token (token.js)

  function tokenRefused(what) {
    window.gcsToken.ask();
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
  // another station's event (joined over Zenoh): its name; this station's own: ""
  function otherStation(e) {
    const here = S.state && S.state.station ? S.state.station.name : null;
    return typeof e.station === "string" && e.station && e.station !== here ? e.station : "";
  }
  function stationEvent(e) {
    if (!e || typeof e !== "object") return;
    const from = otherStation(e);
    const key = from + "|" + e.t + "|" + e.kind + "|" + e.text;
    if (S.seenEvents.has(key)) return;
    S.seenEvents.add(key);
    if (S.seenEvents.size > 2000) S.seenEvents = new Set(Array.from(S.seenEvents).slice(-1000));
    const kind = String(e.kind || "event");
    const text = String(e.text || "");
    const bad = /refus|reject|fail|denied|timeout|error|lost|disconnect|no_answer|did_not_happen/i.test(kind + " " + text);
    log(from ? from + " · " + kind : kind, text, bad ? "refused" : "", e.t);
    // the result of a command the page showed as in progress (its vehicle was still at it)
    const m = kind === "command" && !from && S.awaiting ? /^([A-Z_]+) -> [^:]*: ([A-Z_]+)/.exec(text) : null;
    // the station's follow-up lines (DONE, DID_NOT_HAPPEN, REPLACED) are followStatus's
    const followLine = m && ["IN_PROGRESS", "DONE", "DID_NOT_HAPPEN", "REPLACED"].includes(m[2]);
    const yes = m && (m[2] === "ACCEPTED" || m[2] === "CARRIED_OUT");
    if (m && m[1] === S.awaiting.kind && !followLine && yes && S.followEnded === S.awaiting.what) {
      S.awaiting = null;  // the vehicle's outcome already stands on the status line
    } else if (m && m[1] === S.awaiting.kind && !followLine && yes && S.follow && S.follow.what === S.awaiting.what) {
      S.follow.note = "";  // the agent's part is done; the station goes on following the vehicle
      S.awaiting = null;
    } else if (m && m[1] === S.awaiting.kind && !followLine) {
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
  // a tile layer whose tiles are fetched with the token and shown from their bytes
  const TokenTiles = L.TileLayer.extend({
    createTile(coords, done) {
      const img = document.createElement("img");
      img.alt = "";
      img.setAttribute("role", "presentation");
      const url = this.getTileUrl(coords);
      img.dataset.tile = url;
      const fail = (err) => {
        if (this.options.errorTileUrl) img.src = this.options.errorTileUrl;
        done(err, img);
      };
      api(url).then((r) => (r.ok ? r.blob() : Promise.reject(new Error("HTTP " + r.status)))).then((blob) => {
        const src = URL.createObjectURL(blob);
        img.onload = () => { URL.revokeObjectURL(src); done(null, img); };
        img.onerror = () => { URL.revokeObjectURL(src); img.onerror = null; fail(new Error("not an image")); };
        img.src = src;
      }, fail);
      return img;
    },
  });
  const tokenTileLayer = (url, options) => new TokenTiles(url, options);

  function initMap(cfg) {
    const map = L.map("map", { zoomControl: true, attributionControl: true, worldCopyJump: true });
    S.map = map;
    S.trailRenderer = L.canvas({ padding: 0.3 });
    let tiles = null; // its credit only once a tile has loaded; a grid under it (grid.js)
    if (cfg.tiles) {
      // the station's own tiles need its token, which an <img> cannot send
      const layer = cfg.tiles.startsWith("/") && window.gcsToken.present ? tokenTileLayer : L.tileLayer;
      tiles = layer(cfg.tiles, {
        maxZoom: 21, maxNativeZoom: cfg.tiles_max_zoom || 19, zIndex: 1,
        errorTileUrl: "data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw==",
      }).addTo(map);
    } else {
      $("#map").classList.add("no-tiles");
    }
    const grid = () => window.gcsGrid.add(map, tiles, cfg.attribution || "");
    if (window.gcsGrid) grid(); else window.addEventListener("load", grid);
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

  function agentColour(id) {
    return PALETTE[(Math.abs(Math.trunc(Number(id) || 0)) + PALETTE.length - 1) % PALETTE.length];
  }
  const FLEET_FIELDS = [
    "name", "role", "mode", "armed", "alt", "climb", "groundspeed", "home_dist", "battery", "gps", "ready", "link", "seen",
  ];
  // GPS_FIX_TYPE as an operator reads it
  const FIX_NAMES = ["no GPS", "no fix", "2D", "3D", "DGPS", "RTK float", "RTK fixed", "static", "PPP"];
  function gpsText(a) {
    if (!Number.isInteger(a.gps_fix) && !Number.isInteger(a.satellites)) return "—";
    const fix = Number.isInteger(a.gps_fix) ? FIX_NAMES[a.gps_fix] || "fix " + a.gps_fix : "?";
    return fix + (Number.isInteger(a.satellites) ? " · " + a.satellites + " sat" : "");
  }
  // why an autopilot will not arm: its latest reasons ("PreArm: ..."), the station's advisories
  function notReadyWhy(a) {
    const rows = S.state && Array.isArray(S.state.alerts) ? S.state.alerts : [];
    const why = rows.filter((x) => x && x.agent === a.id && x.kind === "statustext" && x.level === "advisory"
      && typeof x.text === "string").sort((x, y) => (y.last || 0) - (x.last || 0)).slice(0, 4)
      .map((x) => x.text.replace(/^[^:]*\(\d+\): /, ""));
    return why.length ? "the autopilot says: " + why.join("; ") : "the autopilot gives no reason yet";
  }
  function readyText(a) {
    return a.ready === true ? "ready" : a.ready === false ? "not ready" : "—";
  }
  function makeAgent(a) {
    const rec = { data: a, marker: null, el: null, arrow: null, tag: null, trail: null, row: null, view: {} };
    rec.colour = agentColour(a.id);
    const tr = document.createElement("tr");
    tr.dataset.agentId = String(a.id);
    tr.dataset.colour = rec.colour;
    const sw = document.createElement("td");
    sw.innerHTML = '<span class="swatch"></span><span class="lead" hidden>L</span>';
    sw.firstChild.style.background = rec.colour;
    tr.append(sw);
    rec.cells = {};
    for (const f of FLEET_FIELDS) {
      const td = document.createElement("td");
      td.dataset.field = f;
      tr.append(td);
      rec.cells[f] = td;
    }
    tr.tabIndex = 0;
    tr.addEventListener("click", () => select(a.id, true));
    tr.addEventListener("keydown", (ev) => {
      if (ev.key === "Enter" || ev.key === " ") {
        ev.preventDefault();
        select(a.id, true);
      }
    });
    rec.row = tr;
    rec.rowLead = sw.querySelector(".lead");
    S.agents.set(a.id, rec);
    return rec;
  }
  function ensureMarker(rec) {
    if (rec.marker || !S.map) return;
    const a = rec.data;
    rec.trail = L.polyline([], {
      renderer: S.trailRenderer, color: rec.colour, weight: 2, opacity: 0.8, interactive: false,
    }).addTo(S.map);
    rec.marker = L.marker([a.lat, a.lon], {
      icon: L.divIcon({ className: "agent-marker", html: ARROW, iconSize: [32, 32], iconAnchor: [16, 16] }),
      keyboard: false, riseOnHover: true, title: a.name,
    }).addTo(S.map);
    rec.marker.on("click", () => select(a.id, false));
    rec.el = rec.marker.getElement();
    rec.el.dataset.agentId = String(a.id);
    rec.el.dataset.colour = rec.colour;
    rec.el.style.setProperty("--agent", rec.colour);
    rec.arrow = rec.el.querySelector(".arrow");
    rec.tag = rec.el.querySelector(".tag");
    rec.view = {};  // draw everything on the new marker
  }
  // an agent without a position now (a replay sought back before its first fix) has no marker
  function dropMarker(rec) {
    if (rec.marker) rec.marker.remove();
    if (rec.trail) rec.trail.remove();
    rec.marker = rec.trail = rec.el = rec.arrow = rec.tag = null;
  }
  function dropAgent(id) {
    const rec = S.agents.get(id);
    if (!rec) return;
    dropMarker(rec);
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
    (window.gcsStateHooks || []).forEach((f) => { try { f(msg); } catch (err) { console.error(err); } });
    followStatus(msg);
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
    const leads = window.gcsSwarms ? window.gcsSwarms.leaders(st) : new Set();  // every swarm's leader
    const seen = new Set();
    const list = $("#agents tbody");
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
      drawAgent(rec, id === leader || leads.has(id));
    }
    for (const id of Array.from(S.agents.keys())) if (!seen.has(id)) dropAgent(id);
    if (!agents.length && !list.children.length) {
      list.innerHTML = '<tr class="empty"><td colspan="10">no agent yet</td></tr>';
    }
    sortFleet();
    ageFleet();
    if (!S.fitted) fitToAgents();
    drawHeader(st, agents, leader);
    drawElection(agents, leader);
    drawTelemetry();
    (window.gcsDrawHooks || []).forEach((f) => { try { f(st); } catch (err) { console.error(err); } });
  }

  // a swarm's colour (swarms.js): the row, the marker and the trail take it
  function recolour(rec, colour, off) {
    rec.colour = colour;
    rec.row.dataset.colour = colour;
    rec.row.querySelector(".swatch").style.background = colour;
    if (rec.el) {
      rec.el.dataset.colour = colour;
      rec.el.style.setProperty("--agent", colour);
    }
    if (rec.trail) rec.trail.setStyle({ color: off ? OFF_COLOUR : colour });
  }

  // Each agent's last drawn values: only what changed touches the DOM or the map
  // (50 agents at 2-5 snapshots a second stay well inside a frame).
  function drawAgent(rec, isLeader) {
    const a = rec.data;
    const off = !a.connected;
    const selected = S.selected === a.id;
    const v = rec.view;
    const colour = (window.gcsSwarms && window.gcsSwarms.colour(a.id)) || agentColour(a.id);
    if (colour !== rec.colour) recolour(rec, colour, off);
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
        rec.trail.setStyle({ color: off ? OFF_COLOUR : rec.colour, weight: isLeader ? 3 : 2 });
      }
      const trail = Array.isArray(a.trail) ? a.trail.slice(-TRAIL_POINTS) : [];
      const last = trail.length ? trail[trail.length - 1] : null;
      const key = trail.length + (last ? ":" + last[0] + "," + last[1] + ":" + trail[0][0] + "," + trail[0][1] : "");
      if (key !== v.trail) {
        rec.trail.setLatLngs(trail);
        v.trail = key;
      }
    } else if (rec.marker) {
      dropMarker(rec);
    }
    if (isLeader !== v.leader || off !== v.off || selected !== v.selected || a.name !== v.name) {
      const row = rec.row;
      row.classList.toggle("disconnected", off);
      row.classList.toggle("leader", isLeader);
      row.classList.toggle("selected", selected);
      row.dataset.connected = off ? "0" : "1";
      rec.rowLead.hidden = !isLeader;
    }
    drawFleetRow(rec, isLeader);
    v.leader = isLeader;
    v.off = off;
    v.selected = selected;
    v.name = a.name;
  }


  // ---------------------------------------------------------------- fleet table
  function roleText(a, isLeader) {
    if (isLeader) return "leader";
    return String(a.phase || "—").toLowerCase();
  }
  // metres above home (the convention of every altitude typed or read here) when the
  // station knows the agent's home, else the AMSL altitude, marked so
  function altAboveHome(a) {
    return typeof a.alt === "number" && typeof a.home_alt === "number" ? a.alt - a.home_alt : null;
  }
  function altText(a) {
    const rel = altAboveHome(a);
    if (rel !== null) return fmt(rel, 1);
    return typeof a.alt === "number" ? fmt(a.alt, 1) + " AMSL" : "—";
  }
  // the link column: RSSI / remote RSSI as the radio gives them (a hook for loss and margin)
  function linkText(a) {
    const rssi = a.rssi === null || a.rssi === undefined ? "—" : a.rssi + " / " + (a.remrssi ?? "—");
    // the share of its Telemetry the station missed lately (judged with hysteresis)
    return typeof a.loss_pct === "number" ? rssi + " · " + Math.round(a.loss_pct) + " % loss" : rssi;
  }
  // seconds since the station heard the agent, aged by the page's own data age
  function agentAge(a) {
    if (typeof a.last_seen_s !== "number") return null;
    return a.last_seen_s + (S.lastStateAt ? (performance.now() - S.lastStateAt) / 1000 : 0);
  }
  function drawFleetRow(rec, isLeader) {
    const a = rec.data;
    const c = rec.cells;
    setText(c.name, a.name + " (" + a.id + ")");
    setText(c.role, roleText(a, isLeader));
    setText(c.mode, a.vehicle_link === false ? "vehicle link lost" : a.mode || "—");
    setText(c.armed, a.armed === true ? "armed" : a.armed === false ? "disarmed" : "—");
    setText(c.alt, altText(a) + (a.airborne ? " ✈" : ""));
    setText(c.climb, fmt(a.climb, 1));
    setText(c.groundspeed, fmt(a.groundspeed, 1));
    setText(c.home_dist, fmt(a.home_dist, 0));
    setText(c.gps, gpsText(a));
    setText(c.ready, readyText(a));
    c.ready.classList.toggle("bad", a.ready === false);
    c.ready.title = a.ready === false ? notReadyWhy(a) : "";
    setText(c.battery, typeof a.battery === "number" ? fmt(a.battery, 0, "%") : "unknown");
    setText(c.link, linkText(a));
  }
  // the value a header sorts on (null: last either way)
  function sortValue(rec, key) {
    const a = rec.data;
    if (key === "id") return a.id;
    if (key === "swarm") return window.gcsSwarms ? window.gcsSwarms.sortKey(a.id) : null;
    if (key === "name") return String(a.name || "");
    if (key === "role") return a.id === (S.drawn && S.drawn.leader) ? "" : String(a.phase || "~");
    if (key === "armed") return a.armed === true ? 1 : a.armed === false ? 0 : null;
    if (key === "alt") return altAboveHome(a) !== null ? altAboveHome(a) : a.alt;
    if (key === "gps") return Number.isInteger(a.gps_fix) ? a.gps_fix * 1000 + (a.satellites || 0) : null;
    if (key === "ready") return a.ready === true ? 1 : a.ready === false ? 0 : null;
    if (key === "link") return a.rssi;
    if (key === "seen") return a.last_seen_s;
    const v = a[key];
    return v === undefined ? null : v;
  }
  function compareBy(key, dir) {
    return (x, y) => {
      const a = sortValue(x, key);
      const b = sortValue(y, key);
      if (a === null || b === null) return (a === null) - (b === null) || x.data.id - y.data.id;
      const d = typeof a === "number" && typeof b === "number" ? a - b : String(a).localeCompare(String(b));
      return d ? d * dir : x.data.id - y.data.id;
    };
  }
  function sortFleet() {
    const recs = Array.from(S.agents.values()).sort(compareBy(S.sort.key, S.sort.dir));
    const order = recs.map((r) => r.data.id).join(",");
    if (order === S.order) return;
    S.order = order;
    const body = $("#agents tbody");
    for (const r of recs) body.append(r.row);  // moves each row: the table's order
  }
  function initSort() {
    for (const th of document.querySelectorAll("#agents th[data-sort]")) {
      th.tabIndex = 0;
      const go = () => {
        const key = th.dataset.sort;
        S.sort = { key, dir: S.sort.key === key ? -S.sort.dir : 1 };
        for (const h of document.querySelectorAll("#agents th")) h.removeAttribute("aria-sort");
        th.setAttribute("aria-sort", S.sort.dir > 0 ? "ascending" : "descending");
        S.order = "";
        sortFleet();
      };
      th.addEventListener("click", go);
      th.addEventListener("keydown", (ev) => { if (ev.key === "Enter") go(); });
    }
  }
  // the ages in the table, and an agent not heard for AGENT_STALE_S (or disconnected) stale
  function ageFleet() {
    for (const rec of S.agents.values()) {
      const age = agentAge(rec.data);
      const hb = Number(rec.data.hb_s) > 0 ? Number(rec.data.hb_s) : 1;
      const stale = !rec.data.connected || age === null || age > Math.max(AGENT_STALE_S, 3 * hb);
      setText(rec.cells.seen, age === null ? "never" : fmt(age, 1, "s") + (rec.data.connected ? "" : " (lost)"));
      if (stale !== rec.view.stale) {
        rec.view.stale = stale;
        rec.row.classList.toggle("stale", stale);
        rec.row.title = stale ? "stale: these are the last values heard" : "";
        if (rec.el) rec.el.classList.toggle("stale", stale);
      }
    }
    const sel = S.selected !== null ? S.agents.get(S.selected) : null;
    $("#telemetry").classList.toggle("stale", Boolean(sel && sel.view.stale));
  }

  // ---------------------------------------------------------------- honest state
  // how old the page's data is; the station lost when the socket went away with no
  // fresher data since, or nothing came for 2.5 periods of what brings it (the
  // socket's pushes, else the polls), and at least STALE_MIN_MS: at 2 pushes a
  // second, said within 0.5 + 1.25 + one 0.2 s tick = 1.95 s of the last push
  function staleAfterMs() {
    const hz = S.config && Number(S.config.ws_hz) > 0 ? Number(S.config.ws_hz) : 2;
    const period = S.wsStatus === "live" ? 1000 / hz : POLL_MS;
    return Math.max(STALE_MIN_MS, 2.5 * period);
  }
  function freshness() {
    const now = performance.now();
    const age = S.lastStateAt ? (now - S.lastStateAt) / 1000 : null;
    const gone = S.lostAt > S.lastStateAt;
    const stale = age === null ? gone : gone || now - S.lastStateAt > staleAfterMs();
    setText($("#data-age"), age === null ? "no data yet" : "updated " + fmt(age, 1, "s") + " ago");
    $("#data-age").classList.toggle("old", stale);
    if (stale !== S.stale) {
      S.stale = stale;
      document.body.classList.toggle("stale", stale);
      $("#stale-banner").hidden = !stale;
      drawLink();
      if (S.drawn) drawHeader(S.drawn, S.drawn.agents || [], S.drawn.leader || 0);
    }
    drawTelemetry();  // its "last seen" ages too
    if (stale) {
      const what = gone ? "station lost" : "station silent";
      setText($("#stale-banner"), what + ": data " + (age === null ? "never received" : fmt(age, 0, "s") + " old") +
        " (" + (gone ? "reconnecting" : "no state received") + "); the map and the table show the last values known");
    }
    ageFleet();
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
    // a lost station's count is history, and says so
    setText($("#agent-count"), (S.stale ? "last known: " : "") + up + "/" + agents.length + " agents connected");
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
      drawTakeBack(null);
      drawModes(null);
      return;
    }
    const a = rec.data;
    setText($("#telemetry-title"), a.name + " (" + a.id + ")" + (a.connected ? "" : " — disconnected"));
    f("mode", a.vehicle_link === false ? "unknown (vehicle link lost)" : a.mode || "—");
    // unknown is unknown (as in the fleet table): an airborne vehicle whose link dropped is not "disarmed"
    f("armed", a.armed === true ? "armed" : a.armed === false ? "disarmed" : a.vehicle_link === false ? "unknown (vehicle link lost)" : "unknown");
    // altitudes are metres above home (as QGroundControl), AMSL beside; home: the autopilot's
    // (the agent's height above it), else where the station saw it on the ground
    const rel = typeof a.alt === "number" && typeof a.home_alt === "number" ? a.alt - a.home_alt : null;
    f("alt", (rel === null ? "home unknown" : fmt(rel, 1, "m above home")) + " (" + fmt(a.alt, 1, "m AMSL") + ")" + (a.airborne ? " (airborne)" : ""));
    const typed = parseFloat($("#goto-alt").value);
    setText($("#goto-amsl"), !Number.isFinite(typed) ? "" : "alt " + typed + " m above home" + (typeof a.home_alt === "number" ? " = " + (a.home_alt + typed).toFixed(1) + " m AMSL" : " (home unknown here: AMSL not shown)"));
    f("groundspeed", fmt(a.groundspeed, 1, "m/s"));
    f("climb", fmt(a.climb, 1, "m/s"));
    f("home_dist", fmt(a.home_dist, 0, "m"));
    f("gps", gpsText(a));
    f("ready", readyText(a) + (a.ready === false ? " (" + notReadyWhy(a) + ")" : ""));
    f("heading", fmt(a.heading, 0, "°"));
    f("battery", a.battery === null || a.battery === undefined ? "unknown" : fmt(a.battery, 0, "%"));
    f("rssi", (a.rssi ?? "—") + " / " + (a.remrssi ?? "—"));
    f("last_seen", fmt(agentAge(a), 1, "s ago"));
    f("position", hasPosition(a) ? a.lat.toFixed(6) + ", " + a.lon.toFixed(6) : "—");
    f("state", String(a.phase || "—") + (a.leader ? ", leader " + a.leader : "") + (a.holding ? ", holding" : ""));
    const d = a.doing;
    f("doing", d && typeof d === "object"
      ? d.kind + ": " + String(d.state).toLowerCase().replace(/_/g, " ") + (d.text ? ": " + d.text : "") : "—");
    drawTakeBack(a);
    drawModes(a);
  }

  // the mode selector: the modes an operator may choose for one vehicle, by its autopilot
  // (the station's SELECTABLE_MODES; manual and stick modes are not offered)
  const PX4_NAMES = /^(AUTO\.|OFFBOARD$|POSCTL|ALTCTL$|MANUAL$|STABILIZED$)/;
  const SELECTABLE = {
    px4: [["AUTO.LOITER", "hold"], ["AUTO.RTL", "return"], ["AUTO.LAND", "land"], ["OFFBOARD", "swarm"]],
    ardupilot: [["BRAKE", "hold"], ["RTL", "return"], ["LAND", "land"], ["GUIDED", "swarm"]],
  };
  const MODE_WORDS = {
    hold: "its autopilot holds it where it is; it stops following the swarm until you take control back",
    return: "it flies to its home and lands",
    land: "it lands where it is",
    swarm: "the swarm takes control back: it holds where it is",
  };
  function drawModes(a) {
    const row = $("#mode-row");
    const ok = a && a.connected && a.vehicle_link !== false && typeof a.mode === "string" && a.mode
      && !(S.config && S.config.replay);
    row.hidden = !ok;
    if (!ok) return;
    const family = PX4_NAMES.test(a.mode) ? "px4" : "ardupilot";
    const sel = $("#mode-select");
    if (sel.dataset.family !== family) {
      sel.dataset.family = family;
      sel.replaceChildren(...SELECTABLE[family].map(([m, what]) => new Option(m + " (" + what + ")", m)));
    }
  }
  async function setMode() {
    const rec = S.selected !== null ? S.agents.get(S.selected) : null;
    if (!rec || S.confirming) return;
    const a = rec.data, mode = $("#mode-select").value;
    const family = $("#mode-select").dataset.family;
    const what = (SELECTABLE[family] || []).find((x) => x[0] === mode);
    if (!what) return;
    const text = "Switch " + agentName(a.id) + " from " + (a.mode || "an unknown mode") + " to " + mode + "? " +
      MODE_WORDS[what[1]].charAt(0).toUpperCase() + MODE_WORDS[what[1]].slice(1) + ".";
    const dlg = $("#confirm");
    setText($("#confirm-text"), text);
    setText($("#confirm-ok"), "Switch to " + mode);
    dlg.dataset.kind = "set_mode";
    dlg.dataset.target = String(a.id);
    dlg.returnValue = "";
    S.confirming = true;
    const ok = await new Promise((resolve) => {
      dlg.addEventListener("close", () => { S.confirming = false; resolve(dlg.returnValue === "ok"); }, { once: true });
      dlg.showModal();
      $("#confirm-cancel").focus();
    });
    if (!ok) {
      log("cancelled", "set mode " + mode + " → " + agentName(a.id) + ": not sent");
      return;
    }
    await command({ target: a.id, kind: "set_mode", mode });
  }

  // after an autopilot failsafe (the agent's control_lost): what happened, and the way back
  function swarmTask(a) {
    const st = S.drawn || {};
    const tasks = st.swarm_tasks && typeof st.swarm_tasks === "object" ? st.swarm_tasks : {};
    const t = tasks[String(a.leader)] || (st.task && st.task.leader === a.leader ? st.task : null);
    return t && typeof t.heading === "number" ? t : null;
  }
  function drawTakeBack(a) {
    const box = $("#take-back");
    const lost = a && a.control_lost === true && a.connected && !(S.config && S.config.replay);
    box.hidden = !lost;
    if (!lost) return;
    setText($("#take-back-text"), agentName(a.id) + ": its autopilot flies it (mode " + (a.mode || "unknown") +
      "), after a failsafe or a mode chosen here: it is not following the swarm and holds no command of ours.");
    box.querySelector('[data-take="follow"]').hidden = !swarmTask(a);
  }
  async function takeBack(kind) {
    const rec = S.selected !== null ? S.agents.get(S.selected) : null;
    if (!rec) return;
    const a = rec.data, who = agentName(a.id);
    const task = swarmTask(a);
    const text = kind === "stop" ? "Take control of " + who + " back? It holds where it is."
      : kind === "land" ? "Land " + who + " where it is?"
      : "Take control of " + who + " back and have its swarm fly its formation again (heading " + task.heading + "°)?";
    const dlg = $("#confirm");
    if (S.confirming) return;
    setText($("#confirm-text"), text);
    setText($("#confirm-ok"), kind === "stop" ? "Take control" : kind === "land" ? "Land" : "Resume");
    dlg.dataset.kind = "take-back-" + kind;
    dlg.dataset.target = String(a.id);
    dlg.returnValue = "";
    S.confirming = true;
    const ok = await new Promise((resolve) => {
      dlg.addEventListener("close", () => { S.confirming = false; resolve(dlg.returnValue === "ok"); }, { once: true });
      dlg.showModal();
      $("#confirm-cancel").focus();
    });
    if (!ok) {
      log("cancelled", text.replace(/\?$/, "") + ": not sent");
      return;
    }
    if (kind === "land") {
      await command({ target: a.id, kind: "land" });
      return;
    }
    const r = await command({ target: a.id, kind: "stop" });
    const took = r && Array.isArray(r.results) && r.results.some((x) => /^(accepted|carried_out)$/i.test(String(x.result)));
    if (kind === "follow" && took) {
      const several = S.drawn && Array.isArray(S.drawn.swarms) && S.drawn.swarms.length > 1;
      await command(Object.assign({ target: "swarm", kind: "follow", heading: task.heading }, several ? { swarm: a.leader } : {}));
    }
  }

  function select(id, pan) {
    S.selected = id;
    for (const [aid, rec] of S.agents) {
      rec.row.classList.toggle("selected", aid === id);
      if (rec.el) rec.el.classList.toggle("selected", aid === id);
    }
    const rec = id !== null ? S.agents.get(id) : null;
    if (rec && pan && rec.marker && S.map) S.map.panTo(rec.marker.getLatLng());
    // the go-to altitude (above home) follows the selected agent until the operator types one:
    // its own height above home when flying, 10 m on the ground
    if (rec && !S.altTyped) {
      const d = rec.data;
      const flying = d.airborne && typeof d.alt === "number" && typeof d.home_alt === "number";
      $("#goto-alt").value = String(flying ? Math.round(d.alt - d.home_alt) : 10);
    }
    drawTelemetry();
    drawTarget();
    if (S.drawn) drawElection(S.drawn.agents || [], S.drawn.leader || 0);
  }

  // ---------------------------------------------------------------- live link
  function setLink(status) {
    S.wsStatus = status;
    drawLink();
  }
  // the pill says what the data says: an open socket that brings no state (a frozen
  // station) is "silent" in red, never a green "live" beside the "station silent" banner
  function drawLink() {
    const el = $("#link-status");
    const status = S.wsStatus === "live" && S.stale ? "silent" : S.wsStatus;
    el.dataset.status = status;
    el.textContent = status;
    if (S.replay) drawReplay(S.replay);  // a replay shows "REPLAY" and the capture's time, not "live"
  }

  function connect() {
    const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
    let ws;
    try {
      ws = new WebSocket(url, window.gcsToken.protocols());
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
    S.lostAt = performance.now();  // the data is stale until a fresher state arrives
    setLink("reconnecting");
    startPolling();
    setTimeout(connect, S.backoff);
    S.backoff = Math.min(S.backoff * 2, 5000);
  }
  function startPolling() {
    if (S.pollTimer) return;
    const poll = async () => {
      try {
        const r = await api("/api/state", { cache: "no-store" });
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
        // (delta.js loads before this file; without it a delta is a gap: the whole state is asked)
        const st = window.gcsDelta ? window.gcsDelta.next(S.model, S.model ? S.model.seq : null, msg) : null;
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
    return api("/api/command", {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(cmd),
    }).then(async (r) => {
      let body = {};
      try {
        body = await r.json();
      } catch (err) { /* not JSON */ }
      return Object.assign({ status: r.status }, body);
    }, (err) => {
      console.error(err);  // the browser's own words ("TypeError: Failed to fetch") are for the console
      return { status: 0, error: "the station did not answer (is it running, and is this its address?)" };
    });
  }

  function describe(cmd) {
    const who = cmd.target !== "swarm" ? agentName(cmd.target)
      : window.gcsSwarms ? window.gcsSwarms.name(cmd) : "swarm";
    let what = cmd.kind;
    if (cmd.kind === "goto" || cmd.kind === "waypoint") what += " " + cmd.lat.toFixed(6) + ", " + cmd.lon.toFixed(6) + " alt " + cmd.alt + " m above home";
    if (cmd.kind === "takeoff") what += " to " + cmd.alt + " m above home";
    if (cmd.kind === "follow") what += " heading " + cmd.heading + "°";
    if (cmd.kind === "set_mode") what = "set mode " + cmd.mode;
    return what + " → " + who;
  }

  function report(cmd, r) {
    const what = describe(cmd);
    const results = Array.isArray(r.results) ? r.results : [];
    // an answer per addressee (a 504: some never answered) is read agent by agent below
    const err = results.length ? null : r.error || (r.status >= 400 ? r.reason || "refused (" + r.status + ")" : null);
    if (err && !r.status) {  // never reached the station: not sent, not refused
      log("error", what + ": not sent: " + err, "error");
      status(what + ": not sent: " + err, false);
      return;
    }
    if (err) {
      log("refused", what + ": " + err, "refused");
      status(what + ": refused: " + err, false);
      return;
    }
    const bad = [];
    const busy = [];
    const silent = [];
    for (const x of results) {
      const res = String(x.result || "");
      // NO_ANSWER: the agent never answered (it may not have heard): not a refusal
      if (/^no_answer$/i.test(res)) {
        silent.push(agentName(x.agent));
        continue;
      }
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
    const unanswered = silent.length ? "no answer from " + silent.join(", ") + " (it may not have heard)" : "";
    if (silent.length) log("no answer", what + ": " + unanswered, "pending");
    if (bad.length) status(what + ": refused: " + bad.join("; ") + (unanswered ? "; " + unanswered : ""), false);
    else if (silent.length) status(what + ": " + unanswered, false, "pending");
    else if (busy.length) {
      S.awaiting = { kind: String(cmd.kind).toUpperCase(), what };
      status(what + ": in progress: " + busy.join("; ") + " (the result follows in the log)", false, "pending");
    } else if (r.ok === false) status(what + ": not done", false);
    else if (results.some((x) => x.result === "CARRIED_OUT")) status(what + ": carried out (no answer; the telemetry shows it)", true);
    else status(what + ": accepted", true);
    // the station follows what the vehicle does with it: the status goes on from "accepted"
    if (!bad.length && Number.isInteger(r.request) && FOLLOWED.includes(String(cmd.kind))) {
      // request ids are per station (and per radio channel): the agents it went to, too
      // the answer's own words stay in front while it goes on: the agent's "in progress: taking
      // off to 10 m", the station's "carried out"; a plain "accepted" is what following means
      const note = busy.length ? "in progress: " + busy.join("; ")
        : results.some((x) => x.result === "CARRIED_OUT") ? "carried out (no answer; the telemetry shows it)" : "";
      S.follow = { request: r.request, what, note, agents: cmd.target === "swarm" ? null : results.map((x) => x.agent) };
      S.followEnded = null;
    }
  }
  const FOLLOWED = ["arm", "disarm", "stop", "takeoff", "goto", "land", "return", "set_mode"];
  // a followed command's state on its agents' rows (the station's "doing")
  function followStatus(st) {
    const f = S.follow;
    if (!f || !st || !Array.isArray(st.agents)) return;
    const rows = st.agents.filter((a) => a.doing && a.doing.request === f.request && (!f.agents || f.agents.includes(a.id)));
    if (!rows.length) return;
    const by = (s) => rows.filter((a) => a.doing.state === s);
    const name = (a) => (rows.length > 1 ? a.name + ": " : "");
    const bad = by("DID_NOT_HAPPEN"), going = by("IN_PROGRESS"), done = by("DONE"), gone = by("REPLACED");
    let text;
    const details = (list) => list.map((a) => (a.doing.text ? ": " + name(a) + a.doing.text : "")).join(";");
    const front = f.note ? f.note + "; " : "";
    if (bad.length) text = [f.what + ": did not happen: " + bad.map((a) => name(a) + a.doing.text).join("; "), false];
    else if (going.length) text = [f.what + ": " + front + "in progress" + details(going), false, "pending"];
    else if (done.length) text = [f.what + ": " + (f.note.startsWith("carried") ? front : "") + "done" + details(done), true];
    else if (gone.length) text = [f.what + ": replaced " + gone[0].doing.text, false, "pending"];
    if (!text || f.shown === text[0]) return;
    f.shown = text[0];
    status(text[0], text[1], text[2]);
    if (!going.length) {
      S.followEnded = f.what;  // the vehicle's outcome is the last word (a late "accepted" does not undo it)
      S.follow = null;
    }
  }

  async function command(cmd) {
    S.follow = null;  // the status line is this command's now (the last one's goes on in the panel)
    status(describe(cmd) + ": sending…", true);
    const r = await sendCommand(cmd);
    report(cmd, r);
    return r;
  }

  function localRefusal(text) {
    S.follow = null;
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
      const cmd = { target: S.selected, kind, lat, lon, alt };
      if (fenceRefused(cmd)) return null;
      placeTarget(lat, lon);
      command(cmd);
    });
    $("#fit-swarm").addEventListener("click", fitToAgents);
    $("#goto-alt").addEventListener("input", () => { S.altTyped = true; drawTelemetry(); });
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
        const to = $("#cmd-target").value;  // "selected", "swarm" (all), "swarm:<leader id>" (swarms.js)
        if (!to.startsWith("swarm")) {
          if (S.selected === null) return localRefusal(kind + ": select an agent first");
          target = S.selected;
        }
        const cmd = { target, kind };
        if (to.startsWith("swarm:")) cmd.swarm = Number(to.slice(6));
        if (kind === "takeoff") {
          cmd.alt = parseFloat($("#takeoff-alt").value);
          if (!Number.isFinite(cmd.alt)) return localRefusal("take off: altitude must be a number");
          if (fenceRefused(cmd)) return null;
        }
        if (kind === "follow") {
          cmd.heading = parseFloat($("#follow-heading").value);
          if (!Number.isFinite(cmd.heading)) return localRefusal("follow: heading must be a number");
        }
        const why = window.gcsSwarms ? window.gcsSwarms.refusal(cmd) : null;  // follow to several swarms
        if (why) return localRefusal(why);
        confirmed(cmd);
      });
    }
    initCommandSafety();
  }

  // ---------------------------------------------------------------- the geofence
  // the station's (GET /api/config): a take-off or a target outside it is refused here,
  // before any confirmation, with the station's own words (the station checks it again
  // before sending, and the agent before flying). The radius only where the page knows
  // the agent's home (where the station saw it on the ground), as the station does.
  function fenceRefusal(cmd) {
    const f = S.config && S.config.fence;
    if (!f || !["takeoff", "goto", "waypoint"].includes(cmd.kind)) return null;
    const alt = cmd.alt;
    if (alt < f.floor_m) return "altitude " + alt + " m above home is below the floor (" + f.floor_m + " m above home)";
    if (alt > f.ceiling_m) return "altitude " + alt + " m above home is above the ceiling (" + f.ceiling_m + " m)";
    if (cmd.kind === "takeoff" || cmd.target === "swarm" || !window.gcsPlan) return null;
    const rec = S.agents.get(cmd.target);
    const home = rec && Array.isArray(rec.data.home) ? rec.data.home : null;
    if (!home) return null;
    const d = window.gcsPlan.inverse(home[0], home[1], cmd.lat, cmd.lon)[0];
    return d > f.radius_m ? "target " + Math.round(d) + " m from home, beyond the radius (" + f.radius_m + " m)" : null;
  }
  function fenceRefused(cmd) {
    const why = fenceRefusal(cmd);
    if (why) localRefusal(cmd.kind + " refused by the station's geofence: " + why);
    return Boolean(why);
  }

  // ---------------------------------------------------------------- safe commands
  // the addressees, as the dialog names them: "5 agents", "agent2 (2)"
  function addressees(cmd) {
    if (cmd.target !== "swarm") return agentName(cmd.target);
    if (window.gcsSwarms && window.gcsSwarms.addressees(cmd)) return window.gcsSwarms.addressees(cmd);
    const n = S.drawn && Array.isArray(S.drawn.agents) ? S.drawn.agents.filter((a) => a.connected).length : 0;
    if (cmd.kind === "follow") return "the swarm (through its leader)";
    return n === 1 ? "1 agent" : n + " agents";
  }
  function confirmText(cmd) {
    let text = (VERBS[cmd.kind] || cmd.kind) + " " + addressees(cmd);
    if (cmd.kind === "takeoff") text += " to " + cmd.alt + " m above home";
    if (cmd.kind === "follow") text += ", heading " + cmd.heading + "°";
    text += "?";
    // the table's agents the command will not reach (the station sends to connected ones)
    const agents = S.drawn && Array.isArray(S.drawn.agents) ? S.drawn.agents : [];
    const away = cmd.target === "swarm" && cmd.kind !== "follow" && !(window.gcsSwarms && window.gcsSwarms.addressees(cmd))
      ? agents.filter((a) => !a.connected).map((a) => agentName(a.id)) : [];
    if (away.length) text += " Not connected, will not get it: " + away.join(", ") + ".";
    return text;
  }
  // every command to the whole swarm and land, return, disarm, take-off to anyone: ask first
  function confirmed(cmd) {
    const swarm = cmd.target === "swarm";
    if (!swarm && !CONFIRM_KINDS.has(cmd.kind)) return command(cmd);
    if (S.confirming) return null;
    const dlg = $("#confirm");
    setText($("#confirm-text"), confirmText(cmd));
    setText($("#confirm-ok"), VERBS[cmd.kind] || cmd.kind);
    dlg.dataset.kind = cmd.kind;
    dlg.dataset.target = String(cmd.target);
    S.confirming = true;
    dlg.returnValue = "";
    return new Promise((resolve) => {
      dlg.addEventListener("close", () => {
        S.confirming = false;
        if (swarm) $("#cmd-target").value = "selected";  // a swarm (or every one) is never left chosen
        drawTarget();
        if (dlg.returnValue === "ok") resolve(command(cmd));
        else {
          log("cancelled", describe(cmd) + ": not sent");
          resolve(null);
        }
      }, { once: true });
      dlg.showModal();
      $("#confirm-cancel").focus();  // Enter on an unread dialog cancels
    });
  }
  // the command buttons say whom they address, and wait for a selected agent
  function drawTarget() {
    const swarm = $("#cmd-target").value.startsWith("swarm");
    const none = !swarm && S.selected === null;
    const rec = S.selected !== null ? S.agents.get(S.selected) : null;
    const who = window.gcsSwarms && swarm ? window.gcsSwarms.toText($("#cmd-target").value) : "every agent";
    setText($("#cmd-to"), swarm ? who : none ? "select an agent" : rec ? "→ " + agentName(S.selected) : "");
    $("#cmd-to").classList.toggle("missing", none);
    if (S.config && S.config.replay) return;
    for (const b of document.querySelectorAll("#commands button[data-kind]")) {
      b.disabled = none;
      b.title = none ? "select an agent (in the table or on the map)" : "";
    }
  }
  function initCommandSafety() {
    $("#cmd-target").addEventListener("change", drawTarget);
    $("#mode-set").addEventListener("click", setMode);
    for (const b of document.querySelectorAll("#take-back button[data-take]")) {
      b.addEventListener("click", () => takeBack(b.dataset.take));
    }
    // one click: holding where they are is the safe answer to a surprise
    $("#hold-all").addEventListener("click", () => command({ target: "swarm", kind: "stop" }));
    drawTarget();
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
    const radio = r.radio && typeof r.radio === "object" ? r.radio : null;
    setText($("#replay-time"), mmss(r.position_s) + " / " + mmss(r.duration_s)
      + (radio ? " · radio RSSI " + radio.rssi + "/" + radio.remrssi + " noise " + radio.noise + "/" + radio.remnoise : ""));
    if (typeof r.time === "number") {
      // the header tells a replay from a live station, with the capture's own time
      const el = $("#link-status");
      if (S.wsStatus === "live") {
        el.dataset.status = "replay";
        setText(el, "REPLAY " + clock(r.time));
      }
      el.dataset.time = String(r.time);
      el.title = "replay of a capture: " + new Date(r.time * 1000).toLocaleString();
    }
    if (typeof r.seeks === "number" && r.seeks !== S.replaySeeks) {
      // a seek: the station rebuilt its log up to the new position; the next state redraws it
      if (S.replaySeeks !== undefined) {
        $("#log").replaceChildren();
        S.seenEvents = new Set();
        for (const id of Array.from(S.agents.keys())) dropAgent(id);  // markers and trails: redrawn as of then
        if (S.state && S.state.replay && S.state.replay.seeks === r.seeks && Array.isArray(S.state.events)) {
          S.state.events.forEach(stationEvent);
        }
      }
      S.replaySeeks = r.seeks;
    }
  }
  async function replayAction(action, value) {
    try {
      const body = value === undefined ? { action } : { action, value };
      const r = await api("/api/replay", {
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
    for (const el of document.querySelectorAll("#commands button, #goto button, #hold-all")) {
      el.disabled = true;
      el.title = "replay: commands are disabled while a capture plays";
    }
    $("#replay-play").addEventListener("click", () => replayAction(S.replay && S.replay.playing ? "pause" : "play"));
    $("#replay-speed").addEventListener("change", (ev) => replayAction("speed", parseFloat(ev.target.value)));
    $("#replay-seek").addEventListener("change", (ev) => replayAction("seek", parseFloat(ev.target.value)));
    const poll = async () => {
      if (performance.now() - S.replayAt < 2 * POLL_MS) return;  // pushed over the socket
      try {
        const r = await api("/api/replay", { cache: "no-store" });
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
    get map() { return S.map; },  // plan.js draws its layers on it
    get config() { return S.config; },
    get markers() { let n = 0; for (const r of S.agents.values()) if (r.marker) n += 1; return n; },
    get agents() { return Array.from(S.agents.keys()); },
    get selected() { return S.selected; },
    get leader() { return S.drawn ? S.drawn.leader || 0 : 0; },
    get state() { return S.drawn; },  // the newest state drawn (swarms.js)
    drawTarget() { drawTarget(); },
    agentName(id) { return agentName(id); },
    get stateCount() { return S.stateCount; },
    get lastStateTime() { return S.lastStateTime; },
    get wsStatus() { return S.wsStatus; },
    get stale() { return S.stale; },
    trailColour(id) {
      const r = S.agents.get(id);
      return r && r.trail ? r.trail.options.color : null;
    },
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
      const r = await api("/api/config", { cache: "no-store" });
      if (r.ok) cfg = Object.assign(cfg, await r.json());
      else if (r.status === 401) tokenRefused("GET /api/config");
      else log("error", "GET /api/config: " + r.status, "error");
    } catch (err) {
      log("error", "GET /api/config failed: " + err, "error");
    }
    S.config = cfg;
    window.gcsFence = cfg.fence || null;  // plan.js draws it around each home
    if (cfg.station) setText($("#station"), (cfg.station.name || "station") + " #" + (cfg.station.id ?? "?"));
    initMap(cfg);
    initSort();
    initControls();
    if (cfg.replay) initReplay();
    select(null, false);
    connect();
    setInterval(freshness, 200);
  }
  start();
})();
