/* Ground station page: the alert banner.
 *
 * Theory of operation
 * -------------------
 * The station keeps the alerts (battery, link, vehicle link, autopilot STATUSTEXT,
 * refused commands, separation holds) and sends them in every state snapshot as
 * "alerts": [{id, kind, agent, level, text, raised, cleared, acked, count}]. This file
 * shows every unacknowledged one in a banner under the top bar, most severe and
 * newest first, with an "Acknowledge" button each and "Acknowledge all"; an
 * acknowledgement is POST /api/alerts/ack {"id": N} (with the page's token,
 * token.js), hidden at once and confirmed by the next snapshot. A refused
 * acknowledgement lands in the banner's own status line. The alerts' lines in the
 * event log are the station's events (app.js draws them).
 *
 * Other stations' alerts (a station joined to others over Zenoh, issue 16) come in
 * the same list with the "station" that raised it: shown marked with that station's
 * name, keyed by station and id (ids are per station), and acknowledged there
 * (POST {"id": N, "station": name}: this station passes it on; the other station's
 * next state shows it acknowledged). An alert without a station, or with this one's
 * name, is this station's own.
 *
 * It hooks into app.js through window.gcsStateHooks (called with each snapshot) and
 * loads its own stylesheet (/static/alerts.css). Text is only ever set as text.
 *
 * Stable hooks for tests: #alerts-banner[data-count], #alerts-banner .alert[data-alert-id]
 * [data-level][data-kind][data-station], .alert-station, button.alert-ack,
 * #alerts-ack-all, window.gcsAlerts.
 */
(function () {
  "use strict";

  const SHOWN_MAX = 6;  // more are summarised as "and N more"
  const A = { alerts: [], hidden: new Set(), banner: null, list: null, more: null, note: null, here: "" };

  const css = document.createElement("link");
  css.rel = "stylesheet";
  css.href = "/static/alerts.css";
  document.head.appendChild(css);

  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function build() {
    const b = el("section", "alerts-banner");
    b.id = "alerts-banner";
    b.setAttribute("role", "alert");
    b.setAttribute("aria-live", "assertive");
    b.hidden = true;
    b.dataset.count = "0";
    const head = el("div", "alerts-head");
    head.append(el("strong", "", "Alerts"));
    const all = el("button", "alert-ack-all", "Acknowledge all");
    all.type = "button";
    all.id = "alerts-ack-all";
    all.addEventListener("click", () => visible().forEach((a) => ack(a.id, a.station)));
    A.note = el("span", "alerts-note");
    head.append(A.note, all);
    A.list = el("ul", "alerts-list");
    A.more = el("div", "alerts-more");
    b.append(head, A.list, A.more);
    const top = document.getElementById("topbar");
    if (top && top.parentNode) top.parentNode.insertBefore(b, top.nextSibling);
    else document.body.prepend(b);
    A.banner = b;
  }

  function valid(a) {
    return a && typeof a === "object" && Number.isInteger(a.id) && typeof a.text === "string";
  }

  // another station's alert: its name; this station's own: null
  function remote(a) {
    return typeof a.station === "string" && a.station && a.station !== A.here ? a.station : null;
  }
  function key(id, station) {
    return (station || "") + ":" + id;
  }

  function visible() {
    return A.alerts.filter((a) => !a.acked && !A.hidden.has(key(a.id, a.station)));
  }

  function when(t) {
    return typeof t === "number" ? new Date(t * 1000).toLocaleTimeString() : "";
  }

  function draw() {
    if (!A.banner) build();
    const open = visible().sort((x, y) =>
      (y.level === "critical") - (x.level === "critical") || (y.raised || 0) - (x.raised || 0));
    A.banner.hidden = open.length === 0;
    A.banner.dataset.count = String(open.length);
    A.banner.classList.toggle("critical", open.some((a) => a.level === "critical"));
    A.list.replaceChildren(...open.slice(0, SHOWN_MAX).map(row));
    A.more.textContent = open.length > SHOWN_MAX ? "and " + (open.length - SHOWN_MAX) + " more" : "";
  }

  function row(a) {
    const li = el("li", "alert");
    li.dataset.alertId = String(a.id);
    li.dataset.level = a.level === "critical" ? "critical" : "warning";
    li.dataset.kind = String(a.kind || "");
    li.dataset.station = a.station || "";
    li.append(el("span", "alert-level", li.dataset.level === "critical" ? "CRITICAL" : "WARNING"));
    if (a.station) li.append(el("span", "alert-station", "station " + a.station));
    li.append(el("span", "alert-time", when(a.raised)));
    const count = Number.isInteger(a.count) && a.count > 1 ? " (×" + a.count + ")" : "";
    const over = a.cleared !== null && a.cleared !== undefined && a.kind !== "statustext" && a.kind !== "command"
      ? " — over" : "";
    li.append(el("span", "alert-text", a.text + count + over));
    const b = el("button", "alert-ack", "Acknowledge");
    b.type = "button";
    b.addEventListener("click", () => ack(a.id, a.station));
    li.append(b);
    return li;
  }

  async function ack(id, station) {
    A.hidden.add(key(id, station));
    draw();
    let r;
    const body = station ? { id, station } : { id };
    try {
      r = await window.gcsToken.fetch("/api/alerts/ack", {
        method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
      });
    } catch (err) {
      r = null;
    }
    if (r && r.ok) {
      A.note.textContent = "";
      return;
    }
    let why = r ? "HTTP " + r.status : "station unreachable";
    try {
      if (r) why = (await r.json()).error || why;
    } catch (err) { /* not JSON */ }
    A.hidden.delete(key(id, station));
    A.note.textContent = "acknowledgement refused: " + why;
    draw();
  }

  function onState(st) {
    if (!st || !Array.isArray(st.alerts)) return;  // a push without alerts keeps the last ones
    if (st.station && typeof st.station.name === "string") A.here = st.station.name;
    // each alert's station: another station's name, or "" (this station's own)
    A.alerts = st.alerts.filter(valid).map((a) => ({ ...a, station: remote(a) || "" }));
    const ids = new Set(A.alerts.map((a) => key(a.id, a.station)));
    for (const k of A.hidden) if (!ids.has(k)) A.hidden.delete(k);
    draw();
  }

  window.gcsStateHooks = window.gcsStateHooks || [];
  window.gcsStateHooks.push(onState);
  window.gcsAlerts = Object.freeze({
    get open() { return visible().map((a) => a.id); },
    get openByStation() { return visible().map((a) => ({ id: a.id, station: a.station })); },
    ack,
  });
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", draw);
  else draw();
})();
