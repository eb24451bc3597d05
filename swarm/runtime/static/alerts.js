/* Ground station page: the alert banner.
 *
 * Theory of operation
 * -------------------
 * The station keeps the alerts (battery, link, vehicle link, autopilot STATUSTEXT,
 * refused commands, separation holds) and sends them in every state snapshot as
 * "alerts": [{id, kind, agent, level, text, raised, cleared, acked, count}]. This file
 * shows every unacknowledged one in a banner under the top bar, most severe and
 * newest first, with an "Acknowledge" button each and "Acknowledge all"; an
 * acknowledgement is POST /api/alerts/ack {"id": N} (the page's cookie carries the
 * token), hidden at once and confirmed by the next snapshot. A refused
 * acknowledgement lands in the banner's own status line. The alerts' lines in the
 * event log are the station's events (app.js draws them).
 *
 * It hooks into app.js through window.gcsStateHooks (called with each snapshot) and
 * loads its own stylesheet (/static/alerts.css). Text is only ever set as text.
 *
 * Stable hooks for tests: #alerts-banner[data-count], #alerts-banner .alert[data-alert-id]
 * [data-level][data-kind], button.alert-ack, #alerts-ack-all, window.gcsAlerts.
 */
(function () {
  "use strict";

  const SHOWN_MAX = 6;  // more are summarised as "and N more"
  const A = { alerts: [], hidden: new Set(), banner: null, list: null, more: null, note: null };

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
    all.addEventListener("click", () => visible().forEach((a) => ack(a.id)));
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

  function visible() {
    return A.alerts.filter((a) => !a.acked && !A.hidden.has(a.id));
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
    li.append(el("span", "alert-level", li.dataset.level === "critical" ? "CRITICAL" : "WARNING"));
    li.append(el("span", "alert-time", when(a.raised)));
    const count = Number.isInteger(a.count) && a.count > 1 ? " (×" + a.count + ")" : "";
    const over = a.cleared !== null && a.cleared !== undefined && a.kind !== "statustext" && a.kind !== "command"
      ? " — over" : "";
    li.append(el("span", "alert-text", a.text + count + over));
    const b = el("button", "alert-ack", "Acknowledge");
    b.type = "button";
    b.addEventListener("click", () => ack(a.id));
    li.append(b);
    return li;
  }

  async function ack(id) {
    A.hidden.add(id);
    draw();
    let r;
    try {
      r = await fetch("/api/alerts/ack", {
        method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ id }),
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
    A.hidden.delete(id);
    A.note.textContent = "acknowledgement refused: " + why;
    draw();
  }

  function onState(st) {
    if (!st || !Array.isArray(st.alerts)) return;  // a push without alerts keeps the last ones
    A.alerts = st.alerts.filter(valid);
    const ids = new Set(A.alerts.map((a) => a.id));
    for (const id of A.hidden) if (!ids.has(id)) A.hidden.delete(id);
    draw();
  }

  window.gcsStateHooks = window.gcsStateHooks || [];
  window.gcsStateHooks.push(onState);
  window.gcsAlerts = Object.freeze({
    get open() { return visible().map((a) => a.id); },
    ack,
  });
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", draw);
  else draw();
})();
