/* Ground station page: the plan on the map, and the map's tools.
 *
 * Theory of operation
 * -------------------
 * The station keeps what it knows of the plan (swarm/core/station/plan.py) and sends it
 * in the state: each agent's "route" ([[lat, lon, alt above home]...], its go-to target
 * last; null when it has none: arrived, stopped, refused, never sent), its "home"
 * ([lat, lon] where it was last seen on the ground), and the leader's FOLLOW "task"
 * ({leader, heading, back, side}) with its "slots" ([[member, follows, side]...]). This
 * file draws them as four layers an operator toggles in a small layer control:
 *
 * - Route: a dashed line from the agent through its waypoints, each waypoint numbered;
 * - Targets: a cross on each agent's go-to target (its route's last point);
 * - Slots: each member's formation slot, computed here from the followed agent's
 *   position as the agents do (back metres opposite the swarm heading, side metres to
 *   the member's side), with a thin line from the member to it. Only the task and the
 *   assignments cross the WebSocket (they change rarely); the positions are already
 *   in every state;
 * - Homes: an "H" at each agent's home.
 *
 * The form's cross (where the operator clicked, app.js) hides once a route holds its
 * point (the Targets layer draws it from then on, and not after the route ended).
 *
 * Tools: "Follow swarm" (a toggle: while on, every state that leaves an agent outside
 * the map's view refits the map to the swarm, never zooming in), and "Measure" (click
 * two points: the ellipsoidal distance in metres and the initial bearing in degrees,
 * WGS-84 by Vincenty's inverse formula; a third click starts again; Escape clears and
 * ends the tool; while it is on, map clicks do not move the go-to target). Labels: after
 * each state (at most every 200 ms) the agents' name tags are placed greedily, leader
 * first: right of the marker, else left, below, above; a tag that fits nowhere is
 * hidden and shown while the pointer is on its marker.
 *
 * Hooks into app.js through window.gcsStateHooks and window.gcs.map; loads its own
 * stylesheet (/static/plan.css). Text is only ever set as text.
 *
 * Stable hooks for tests: .plan-route[data-agent-id], .plan-target[data-agent-id],
 * .plan-slot[data-agent-id], .plan-home[data-agent-id], #plan-follow, #plan-measure,
 * #plan-measure-out[data-m][data-deg], window.gcsPlan.
 */
(function () {
  "use strict";

  const LABEL_GAP_MS = 200;
  const WGS_A = 6378137.0;
  const WGS_F = 1 / 298.257223563;
  const P = {
    map: null, layers: null, control: null, last: null, follow: false, sent: new Set(),
    routes: new Map(), targets: new Map(), slots: new Map(), homes: new Map(), fences: new Map(),
    measuring: false, points: [], line: null, out: null, down: null, labelAt: 0, labelQueued: false,
  };

  const css = document.createElement("link");
  css.rel = "stylesheet";
  css.href = "/static/plan.css";
  document.head.appendChild(css);

  // a div icon whose content is a constant (never an agent's text)
  function icon(cls, html, size) {
    return L.divIcon({ className: cls, html, iconSize: [size, size], iconAnchor: [size / 2, size / 2] });
  }
  // run fn(element) now and whenever the item's element is made again (a layer toggled back on)
  function decorate(item, fn) {
    item.decorate = fn;
    item.on("add", () => { const el = item.getElement(); if (el) fn(el); });
    const el = item.getElement && item.getElement();
    if (el) fn(el);
  }
  function redecorate(item) {
    const el = item.getElement();
    if (el && item.decorate) item.decorate(el);
  }

  // ------------------------------------------------------------------ geometry
  // metres north and east of (lat, lon) as [lat, lon] (the ellipsoid's radii of
  // curvature there: exact enough over a formation's tens of metres)
  function offset(lat, lon, north, east) {
    const phi = lat * Math.PI / 180;
    const e2 = WGS_F * (2 - WGS_F);
    const w = Math.sqrt(1 - e2 * Math.sin(phi) ** 2);
    const rn = WGS_A / w;
    const rm = WGS_A * (1 - e2) / (w * w * w);
    return [lat + north / rm * 180 / Math.PI, lon + east / (rn * Math.cos(phi)) * 180 / Math.PI];
  }
  // a member's slot: the followed agent's position, back metres opposite the heading,
  // side metres to the member's side (+1 right of the heading, -1 left)
  function slotOf(followed, task, side) {
    const h = task.heading * Math.PI / 180;
    const fwdN = Math.cos(h), fwdE = Math.sin(h);
    const rightN = -Math.sin(h), rightE = Math.cos(h);
    const n = -task.back * fwdN + side * task.side * rightN;
    const e = -task.back * fwdE + side * task.side * rightE;
    return offset(followed.lat, followed.lon, n, e);
  }
  // Vincenty's inverse on WGS-84: [metres, initial bearing in degrees 0..360)
  function inverse(lat1, lon1, lat2, lon2) {
    const rad = Math.PI / 180, b = WGS_A * (1 - WGS_F);
    const U1 = Math.atan((1 - WGS_F) * Math.tan(lat1 * rad)), U2 = Math.atan((1 - WGS_F) * Math.tan(lat2 * rad));
    const L0 = (lon2 - lon1) * rad;
    const sU1 = Math.sin(U1), cU1 = Math.cos(U1), sU2 = Math.sin(U2), cU2 = Math.cos(U2);
    let lam = L0, sinS = 0, cosS = 1, sig = 0, cos2A = 1, cos2Sm = 0, sinL = 0, cosL = 1;
    for (let i = 0; i < 200; i++) {
      sinL = Math.sin(lam); cosL = Math.cos(lam);
      sinS = Math.hypot(cU2 * sinL, cU1 * sU2 - sU1 * cU2 * cosL);
      if (sinS === 0) return [0, 0];
      cosS = sU1 * sU2 + cU1 * cU2 * cosL;
      sig = Math.atan2(sinS, cosS);
      const sinA = cU1 * cU2 * sinL / sinS;
      cos2A = 1 - sinA * sinA;
      cos2Sm = cos2A ? cosS - 2 * sU1 * sU2 / cos2A : 0;
      const C = WGS_F / 16 * cos2A * (4 + WGS_F * (4 - 3 * cos2A));
      const prev = lam;
      lam = L0 + (1 - C) * WGS_F * sinA * (sig + C * sinS * (cos2Sm + C * cosS * (-1 + 2 * cos2Sm * cos2Sm)));
      if (Math.abs(lam - prev) < 1e-12) break;
    }
    const u2 = cos2A * (WGS_A * WGS_A - b * b) / (b * b);
    const A = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)));
    const B = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)));
    const dS = B * sinS * (cos2Sm + B / 4 * (cosS * (-1 + 2 * cos2Sm * cos2Sm)
      - B / 6 * cos2Sm * (-3 + 4 * sinS * sinS) * (-3 + 4 * cos2Sm * cos2Sm)));
    const az = Math.atan2(cU2 * sinL, cU1 * sU2 - sU1 * cU2 * cosL) / rad;
    return [b * A * (sig - dS), (az + 360) % 360];
  }

  // ------------------------------------------------------------------ layers
  // keep one map item per key in `items`: update the kept ones, add the new, drop the rest
  function sync(items, layer, wanted, make, update) {
    for (const [k, v] of wanted) {
      let it = items.get(k);
      if (!it) {
        it = make(k, v);
        items.set(k, it);
        it.addTo(layer);
      }
      update(it, v, k);
    }
    for (const [k, it] of Array.from(items)) {
      if (!wanted.has(k)) {
        layer.removeLayer(it);
        items.delete(k);
      }
    }
  }
  function isPoint(p) {
    return Array.isArray(p) && Number.isFinite(p[0]) && Number.isFinite(p[1])
      && Math.abs(p[0]) <= 90 && Math.abs(p[1]) <= 180;
  }
  function hasPos(a) {
    return Number.isFinite(a.lat) && Number.isFinite(a.lon) && !(a.lat === 0 && a.lon === 0);
  }
  function colour(id) {
    return (window.gcs && window.gcs.trailColour(id)) || "#3b82f6";
  }

  function drawRoutes(agents) {
    const routes = new Map(), targets = new Map();
    for (const a of agents) {
      if (!Number.isInteger(a.id)) continue;
      const r = Array.isArray(a.route) ? a.route.filter(isPoint) : [];
      if (!r.length) continue;
      const pts = (hasPos(a) ? [[a.lat, a.lon]] : []).concat(r.map((p) => [p[0], p[1]]));
      routes.set(a.id, { pts, wps: r });
      targets.set(a.id, { p: r[r.length - 1], name: a.name });
    }
    sync(P.routes, P.layers.route, routes, (id) => {
      const g = L.layerGroup();
      g.line = L.polyline([], {
        className: "plan-route", color: colour(id), weight: 2, dashArray: "6 6", interactive: false,
      }).addTo(g);
      decorate(g.line, (el) => { el.dataset.agentId = String(id); });
      g.wps = [];
      return g;
    }, (g, v) => {
      g.line.setLatLngs(v.pts);
      const key = JSON.stringify(v.wps);
      if (key === g.key) return;
      g.key = key;
      g.wps.forEach((m) => g.removeLayer(m));
      g.wps = v.wps.slice(0, -1).map((p, i) => L.marker([p[0], p[1]], {
        icon: icon("plan-wp", String(i + 1), 16), interactive: false, keyboard: false,
      }).addTo(g));
    });
    sync(P.targets, P.layers.targets, targets, (id) => {
      const m = L.marker([0, 0], { icon: icon("plan-target", "✕", 22), keyboard: false, zIndexOffset: -500 });
      decorate(m, (el) => {
        el.dataset.agentId = String(id);
        el.title = m.text || "";
      });
      return m;
    }, (m, v) => {
      const key = v.p.join(",") + "," + v.name;
      if (key === m.key) return;
      m.key = key;
      m.setLatLng([v.p[0], v.p[1]]);
      m.text = v.name + ": go-to target, " + v.p[2] + " m above home";
      redecorate(m);
    });
  }

  function drawSlots(st, byId) {
    const want = new Map();
    const t = st.task;
    const ok = t && [t.heading, t.back, t.side].every((x) => Number.isFinite(x) && Math.abs(x) < 1e4);
    if (ok && Array.isArray(st.slots)) {
      for (const s of st.slots) {
        if (!Array.isArray(s) || s.length < 3) continue;
        const [member, follows, side] = s;
        const f = byId.get(follows), m = byId.get(member);
        if (!f || !hasPos(f) || (side !== 1 && side !== -1)) continue;
        want.set(member, { p: slotOf(f, t, side), m: m && hasPos(m) ? [m.lat, m.lon] : null });
      }
    }
    sync(P.slots, P.layers.slots, want, (id) => {
      const g = L.layerGroup();
      g.ring = L.circleMarker([0, 0], {
        className: "plan-slot", radius: 7, color: colour(id), weight: 2, fill: false, interactive: false,
      }).addTo(g);
      decorate(g.ring, (el) => { el.dataset.agentId = String(id); });
      g.tie = L.polyline([], {
        className: "plan-tie", color: colour(id), weight: 1, dashArray: "2 4", interactive: false,
      }).addTo(g);
      return g;
    }, (g, v) => {
      g.ring.setLatLng(v.p);
      g.ring.slot = v.p;
      g.tie.setLatLngs(v.m ? [v.m, v.p] : []);
    });
  }

  function drawHomes(agents) {
    const want = new Map();
    for (const a of agents) if (isPoint(a.home)) want.set(a.id, { p: a.home, name: a.name });
    sync(P.homes, P.layers.homes, want, (id) => {
      // under the agents' markers, and no target for the pointer: a grounded agent sits on its home
      const m = L.marker([0, 0], { icon: icon("plan-home", "H", 18), keyboard: false, interactive: false, zIndexOffset: -1000 });
      decorate(m, (el) => {
        el.dataset.agentId = String(id);
        el.style.borderColor = colour(id);
        el.title = m.text || "";
      });
      return m;
    }, (m, v) => {
      const key = v.p[0] + "," + v.p[1] + "," + v.name;
      if (key === m.key) return;  // a home moves only while its agent is on the ground
      m.key = key;
      m.setLatLng(v.p);
      m.text = v.name + " home";
      redecorate(m);
    });
    // the station's geofence around each home: where a target may be (its radius)
    const fence = window.gcsFence;
    const rings = new Map(fence && fence.radius_m > 0 ? want : []);
    sync(P.fences, P.layers.homes, rings, () => L.circle([0, 0], {
      radius: 1, color: "#e0b040", weight: 1.5, dashArray: "6 6", fill: false, interactive: false,
      className: "plan-fence",
    }), (c, v) => {
      c.setLatLng(v.p);
      c.setRadius(fence.radius_m);
    });
  }

  // The form's own cross (app.js's #goto-target, where the operator clicked) is only a
  // point not sent yet: once a route holds it, the Targets layer draws it, and when that
  // route ends (arrived, replaced) it must not stay behind: hidden while the form holds
  // a point some route held, shown again when the operator picks another.
  function pointKey(lat, lon) {
    return Number(lat).toFixed(6) + "," + Number(lon).toFixed(6);
  }
  function markSent(agents) {
    for (const a of agents) {
      if (!Array.isArray(a.route)) continue;
      for (const p of a.route) if (isPoint(p)) P.sent.add(pointKey(p[0], p[1]));
    }
    while (P.sent.size > 500) P.sent.delete(P.sent.values().next().value);
    const el = document.getElementById("goto-target");
    const lat = document.getElementById("goto-lat"), lon = document.getElementById("goto-lon");
    if (el && lat && lon) el.classList.toggle("plan-sent", P.sent.has(pointKey(lat.value, lon.value)));
  }

  // ------------------------------------------------------------------ follow swarm
  function followSwarm(agents) {
    if (!P.follow) return;
    const pts = agents.filter(hasPos).map((a) => [a.lat, a.lon]);
    if (!pts.length) return;
    const b = L.latLngBounds(pts);
    if (P.map.getBounds().pad(-0.08).contains(b)) return;
    P.map.fitBounds(b.pad(0.25), { animate: false, maxZoom: Math.max(P.map.getZoom(), 3) });
  }

  // ------------------------------------------------------------------ labels
  function placeLabels() {
    P.labelQueued = false;
    P.labelAt = performance.now();
    const els = Array.from(document.querySelectorAll("#map .agent-marker"));
    els.sort((x, y) => (y.dataset.leader === "1") - (x.dataset.leader === "1")
      || (y.classList.contains("selected") - x.classList.contains("selected"))
      || Number(x.dataset.agentId) - Number(y.dataset.agentId));
    const places = ["", "tag-left", "tag-below", "tag-above"];
    const items = els.map((el) => ({ el, tag: el.querySelector(".tag"), box: el.getBoundingClientRect() }))
      .filter((it) => it.tag && it.tag.textContent);
    const taken = items.map((it) => it.box);  // the arrows themselves are never covered
    for (const it of items) {
      const w = it.tag.offsetWidth || 40, h = it.tag.offsetHeight || 14;
      const cx = it.box.left + it.box.width / 2, cy = it.box.top + it.box.height / 2;
      const rects = {
        "": { left: cx + 10, top: cy - 12, right: cx + 10 + w, bottom: cy - 12 + h },
        "tag-left": { left: cx - 10 - w, top: cy - 12, right: cx - 10, bottom: cy - 12 + h },
        "tag-below": { left: cx - w / 2, top: cy + 16, right: cx + w / 2, bottom: cy + 16 + h },
        "tag-above": { left: cx - w / 2, top: cy - 16 - h, right: cx + w / 2, bottom: cy - 16 },
      };
      let chosen = null;
      for (const p of places) {
        const r = rects[p];
        if (!taken.some((o) => o !== it.box && r.left < o.right && o.left < r.right && r.top < o.bottom && o.top < r.bottom)) {
          chosen = p;
          taken.push(r);
          break;
        }
      }
      for (const p of places) if (p) it.tag.classList.toggle(p, p === chosen);
      it.tag.classList.toggle("tag-hidden", chosen === null);
    }
  }
  function queueLabels() {
    if (P.labelQueued) return;
    P.labelQueued = true;
    const wait = Math.max(0, LABEL_GAP_MS - (performance.now() - P.labelAt));
    setTimeout(() => requestAnimationFrame(placeLabels), wait);
  }

  // ------------------------------------------------------------------ measure
  function clearMeasure() {
    P.points = [];
    if (P.line) P.line.setLatLngs([]);
    P.dots.clearLayers();
    P.out.textContent = "";
    delete P.out.dataset.m;
    delete P.out.dataset.deg;
  }
  function setMeasuring(on) {
    P.measuring = on;
    P.measureBtn.classList.toggle("on", on);
    P.measureBtn.setAttribute("aria-pressed", on ? "true" : "false");
    P.map.getContainer().classList.toggle("plan-measuring", on);
    if (!on) clearMeasure();
    else P.out.textContent = "click two points";
  }
  function measureClick(latlng) {
    if (P.points.length >= 2) clearMeasure();
    P.points.push([latlng.lat, latlng.lng]);
    L.circleMarker(latlng, { className: "plan-measure-dot", radius: 4, interactive: false }).addTo(P.dots);
    P.line.setLatLngs(P.points);
    if (P.points.length < 2) {
      P.out.textContent = "click the second point";
      return;
    }
    const [[a, b], [c, d]] = P.points;
    const [m, deg] = inverse(a, b, c, d);
    P.out.dataset.m = m.toFixed(2);
    P.out.dataset.deg = deg.toFixed(2);
    P.out.textContent = (m >= 1000 ? (m / 1000).toFixed(3) + " km" : m.toFixed(1) + " m") + " · " + deg.toFixed(1) + "°";
  }
  // while measuring, a click on the map is the tool's (caught before Leaflet, so the
  // go-to target does not move); a drag is not a click
  function catchClicks() {
    const box = P.map.getContainer();
    document.addEventListener("mousedown", (ev) => { P.down = [ev.clientX, ev.clientY]; }, true);
    document.addEventListener("click", (ev) => {
      if (!P.measuring || !box.contains(ev.target) || ev.target.closest(".leaflet-control")) return;
      ev.stopPropagation();
      const d = P.down;
      if (d && Math.hypot(ev.clientX - d[0], ev.clientY - d[1]) > 5) return;
      measureClick(P.map.mouseEventToLatLng(ev));
    }, true);
    document.addEventListener("keydown", (ev) => {
      if (ev.key === "Escape" && P.measuring) setMeasuring(false);
    });
  }

  // ------------------------------------------------------------------ controls
  function button(bar, id, text, title, onClick) {
    const b = L.DomUtil.create("button", "plan-btn", bar);
    b.id = id;
    b.type = "button";
    b.textContent = text;
    b.title = title;
    b.setAttribute("aria-pressed", "false");
    L.DomEvent.on(b, "click", (ev) => { L.DomEvent.stop(ev); onClick(); });
    return b;
  }
  function initTools() {
    const Tools = L.Control.extend({
      onAdd() {
        const bar = L.DomUtil.create("div", "leaflet-bar plan-tools");
        L.DomEvent.disableClickPropagation(bar);
        P.followBtn = button(bar, "plan-follow", "Follow swarm", "keep every agent in view as they move", () => {
          P.follow = !P.follow;
          P.followBtn.classList.toggle("on", P.follow);
          P.followBtn.setAttribute("aria-pressed", P.follow ? "true" : "false");
          if (P.follow && P.last) followSwarm(P.last.agents || []);
        });
        P.measureBtn = button(bar, "plan-measure", "Measure", "distance and bearing: click two points (Escape clears)", () => setMeasuring(!P.measuring));
        P.out = L.DomUtil.create("div", "plan-measure-out", bar);
        P.out.id = "plan-measure-out";
        P.out.setAttribute("aria-live", "polite");
        return bar;
      },
    });
    new Tools({ position: "topleft" }).addTo(P.map);
  }

  function init(map) {
    P.map = map;
    P.layers = { route: L.layerGroup(), targets: L.layerGroup(), slots: L.layerGroup(), homes: L.layerGroup() };
    Object.values(P.layers).forEach((l) => l.addTo(map));
    P.control = L.control.layers(null, {
      "Route &amp; waypoints": P.layers.route,
      "Go-to targets": P.layers.targets,
      "Formation slots": P.layers.slots,
      "Homes": P.layers.homes,
    }, { collapsed: false, position: "bottomright" }).addTo(map);
    P.control.getContainer().classList.add("plan-layers");
    P.dots = L.layerGroup().addTo(map);
    P.line = L.polyline([], { className: "plan-measure-line", weight: 2, interactive: false }).addTo(map);
    initTools();
    catchClicks();
    map.on("zoomend moveend", queueLabels);
  }

  function onState(st) {
    if (!P.map) {
      if (!window.gcs || !window.gcs.map) return;
      init(window.gcs.map);
    }
    P.last = st;
    const agents = Array.isArray(st.agents) ? st.agents : [];
    const byId = new Map(agents.map((a) => [a.id, a]));
    // after app.js has drawn this state (it draws in the next animation frame)
    requestAnimationFrame(() => {
      if (P.last !== st) return;
      try {
        drawRoutes(agents);
        drawSlots(st, byId);
        drawHomes(agents);
        markSent(agents);
        followSwarm(agents);
      } catch (err) {
        console.error(err);  // a bad value in one state draws nothing new; the next one may
      }
      queueLabels();
    });
  }

  (window.gcsStateHooks = window.gcsStateHooks || []).push(onState);

  window.gcsPlan = Object.freeze({
    get follow() { return P.follow; },
    get measuring() { return P.measuring; },
    get points() { return P.points.map((p) => p.slice()); },  // the measure tool's points
    slot(id) { const g = P.slots.get(id); return g ? g.ring.slot : null; },
    inverse,
  });
})();
