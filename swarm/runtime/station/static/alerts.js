/* Ground station page: the alarm banner, the alarm list, and the alarm sound.
 *
 * Theory of operation
 * -------------------
 * The station manages its alarms (swarm/core/station/alerts.py, after ISA-18.2):
 * one per condition, with its count, first ("raised") and last time, latched until
 * acknowledged, priorities (critical, warning, advisory), shelving, chattering and
 * flood suppression; every state carries them as "alerts": [{id, kind, agent, level,
 * text, raised, last, cleared, acked, count, announced, quiet, shelved_until}] and the
 * rate as "alarm_rate". This file shows:
 *
 * - the banner under the top bar: the alarms to act on (unacknowledged, announced,
 *   not quiet, not advisory), most severe and newest first, in a fixed height (three
 *   rows; it never grows over the map), "and N more" beyond, an "Acknowledge" button
 *   each and "Acknowledge all", and the flood line when the station holds warnings;
 * - the alarm list (the "Alarms" button in the top bar, or the banner's "List"): every
 *   alarm the station sends, advisories, acknowledged, quiet and over ones included,
 *   with its count, first and last time and state; each can be acknowledged, shelved
 *   (10 min or 1 h, a confirmation first) or unshelved;
 * - the sound: a new announcement of a critical alarm (its "announced" time newer than
 *   the page last heard) plays three short tones and says its text with the browser's
 *   own speech when it has one; the "Sound" button switches it (kept in localStorage).
 *   Alarms already standing when the page opens are shown, not sounded.
 *
 * An acknowledgement is POST /api/alerts/ack {"id": N} (with the page's token,
 * token.js), hidden at once and confirmed by the next state; a shelving POST
 * /api/alerts/shelve {"id": N, "seconds": S}. A refusal lands in the banner's and the
 * list's status line as one sentence. Other stations' alarms (issue 16) come with the
 * "station" that raised it: marked, keyed by station and id, acknowledged there; they
 * are shelved by their own station's operator.
 *
 * It hooks into app.js through window.gcsStateHooks (called with each state) and
 * loads its own stylesheet (/static/alerts.css). Text is only ever set as text.
 *
 * Stable hooks for tests: #alerts-banner[data-count], #alerts-banner .alert[data-alert-id]
 * [data-level][data-kind][data-station], .alert-station, button.alert-ack,
 * #alerts-ack-all, #alerts-flood, #alarms-button, #alarms-panel .alarm[data-alert-id]
 * [data-state], button.alarm-shelve, button.alarm-unshelve, #sound-toggle[aria-pressed],
 * window.gcsAlerts (open, openByStation, sounded, spoken, sound, ack, shelve).
 */
(function () {
  "use strict";

  const SHOWN_MAX = 3;  // rows in the banner; more are "and N more"
  const SOUND_KEY = "gcs.sound";
  const A = {
    alerts: [], rate: null, hidden: new Set(), banner: null, list: null, more: null, note: null,
    flood: null, here: "", panel: null, rows: null, pnote: null, button: null, soundBtn: null,
    heard: null, sounded: 0, spoken: [], audio: null,
  };

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
  function button(text, cls, title, onClick) {
    const b = el("button", cls, text);
    b.type = "button";
    if (title) b.title = title;
    b.addEventListener("click", onClick);
    return b;
  }

  function soundOn() {
    try { return localStorage.getItem(SOUND_KEY) !== "off"; } catch (err) { return true; }
  }

  function build() {
    const b = el("section", "alerts-banner");
    b.id = "alerts-banner";
    b.setAttribute("role", "alert");
    b.setAttribute("aria-live", "assertive");
    b.hidden = true;
    b.dataset.count = "0";
    const head = el("div", "alerts-head");
    head.append(el("strong", "", "Alarms"));
    A.note = el("span", "alerts-note");
    const all = button("Acknowledge all", "alert-ack-all", "acknowledge every alarm shown here", () =>
      visible().forEach((a) => ack(a.id, a.station)));
    all.id = "alerts-ack-all";
    head.append(A.note, button("List", "alerts-open", "every alarm, with its count and times", () => openPanel(true)), all);
    A.list = el("ul", "alerts-list");
    A.more = el("div", "alerts-more");
    A.flood = el("div", "alerts-flood");
    A.flood.id = "alerts-flood";
    b.append(head, A.list, A.more, A.flood);
    const top = document.getElementById("topbar");
    if (top && top.parentNode) top.parentNode.insertBefore(b, top.nextSibling);
    else document.body.prepend(b);
    A.banner = b;
    // the top bar's controls: the list and the sound
    A.button = button("Alarms", "alarms-button", "every alarm: acknowledge, shelve", () => openPanel(!A.panel || A.panel.hidden));
    A.button.id = "alarms-button";
    A.soundBtn = button("", "sound-toggle", "the sound of new critical alarms", () => setSound(!soundOn()));
    A.soundBtn.id = "sound-toggle";
    if (top) top.append(A.button, A.soundBtn);
    else document.body.prepend(A.button, A.soundBtn);
    drawSound();
    // the list
    const p = el("aside", "alarms-panel");
    p.id = "alarms-panel";
    p.hidden = true;
    p.setAttribute("aria-label", "alarm list");
    const ph = el("div", "alarms-head");
    ph.append(el("strong", "", "Alarm list"));
    A.pnote = el("span", "alerts-note");
    ph.append(A.pnote, button("Close", "alarms-close", "", () => openPanel(false)));
    A.rows = el("ul", "alarms-rows");
    p.append(ph, A.rows);
    document.body.append(p);
    A.panel = p;
  }

  function openPanel(on) {
    if (!A.panel) build();
    A.panel.hidden = !on;
    if (on) drawPanel();
  }

  function setSound(on) {
    try { localStorage.setItem(SOUND_KEY, on ? "on" : "off"); } catch (err) { /* private mode */ }
    if (on) audio();  // a click: the browser lets the page's audio start now
    drawSound();
  }
  function drawSound() {
    if (!A.soundBtn) return;
    const on = soundOn();
    A.soundBtn.textContent = on ? "Sound on" : "Sound off";
    A.soundBtn.setAttribute("aria-pressed", on ? "true" : "false");
  }

  function audio() {
    const Ctx = window.AudioContext || window.webkitAudioContext;
    if (!Ctx) return null;
    if (!A.audio) {
      try { A.audio = new Ctx(); } catch (err) { return null; }
    }
    if (A.audio.state === "suspended") A.audio.resume().catch(() => {});
    return A.audio;
  }

  // three short tones and the text spoken: a new critical alarm
  function sound(a) {
    if (!soundOn()) return;
    A.sounded += 1;
    const ctx = audio();
    if (ctx) {
      for (let i = 0; i < 3; i++) {
        const o = ctx.createOscillator(), g = ctx.createGain();
        o.frequency.value = 880;
        g.gain.value = 0.2;
        o.connect(g).connect(ctx.destination);
        const t = ctx.currentTime + i * 0.25;
        o.start(t);
        o.stop(t + 0.15);
      }
    }
    const text = "Critical: " + a.text;
    A.spoken.push(text);
    if (window.speechSynthesis && window.SpeechSynthesisUtterance) {
      try { window.speechSynthesis.speak(new SpeechSynthesisUtterance(text)); } catch (err) { /* none */ }
    }
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

  // what the banner shows: to act on now
  function inBanner(a) {
    return !a.acked && !a.quiet && a.level !== "advisory" && a.announced !== null && a.announced !== undefined;
  }
  function visible() {
    return A.alerts.filter((a) => inBanner(a) && !A.hidden.has(key(a.id, a.station)));
  }

  function when(t) {
    return typeof t === "number" ? new Date(t * 1000).toLocaleTimeString() : "";
  }
  const LEVEL_RANK = { critical: 2, warning: 1, advisory: 0 };
  function levelOf(a) {
    return a.level === "critical" || a.level === "advisory" ? a.level : "warning";
  }

  function draw() {
    if (!A.banner) build();
    const open = visible().sort((x, y) =>
      LEVEL_RANK[levelOf(y)] - LEVEL_RANK[levelOf(x)] || (y.announced || 0) - (x.announced || 0));
    const flood = A.rate && A.rate.flood;
    A.banner.hidden = open.length === 0 && !flood;
    A.banner.dataset.count = String(open.length);
    A.banner.classList.toggle("critical", open.some((a) => a.level === "critical"));
    A.list.replaceChildren(...open.slice(0, SHOWN_MAX).map(row));
    A.more.textContent = open.length > SHOWN_MAX ? "and " + (open.length - SHOWN_MAX) + " more: see the list" : "";
    A.flood.textContent = flood
      ? "Alarm flood: " + A.rate.announced + " alarms in " + Math.round(A.rate.window_s / 60) +
        " min; new warnings are listed, not announced (critical ones still are)"
      : "";
    const active = A.alerts.filter((a) => !a.acked && a.level !== "advisory").length;
    A.button.textContent = "Alarms" + (A.alerts.length ? " (" + active + "/" + A.alerts.length + ")" : "");
    A.button.classList.toggle("critical", open.some((a) => a.level === "critical"));
    if (A.panel && !A.panel.hidden) drawPanel();
  }

  function countText(a) {
    return Number.isInteger(a.count) && a.count > 1 ? " (×" + a.count + ", last " + when(a.last) + ")" : "";
  }

  function row(a) {
    const li = el("li", "alert");
    li.dataset.alertId = String(a.id);
    li.dataset.level = levelOf(a);
    li.dataset.kind = String(a.kind || "");
    li.dataset.station = a.station || "";
    li.append(el("span", "alert-level", levelOf(a).toUpperCase()));
    if (a.station) li.append(el("span", "alert-station", "station " + a.station));
    li.append(el("span", "alert-time", when(a.raised)));
    const over = a.cleared !== null && a.cleared !== undefined && a.kind !== "statustext" && a.kind !== "command"
      ? " — over" : "";
    li.append(el("span", "alert-text", a.text + countText(a) + over));
    li.append(button("Acknowledge", "alert-ack", "", () => ack(a.id, a.station)));
    return li;
  }

  // one alarm's state in words (ISA-18.2's: active or over, acknowledged or not, quiet)
  function stateOf(a) {
    const active = a.cleared === null || a.cleared === undefined || a.kind === "statustext" || a.kind === "command"
      ? (a.kind === "statustext" || a.kind === "command" ? "said" : "active") : "over";
    const parts = [active, a.acked ? "acknowledged" : "unacknowledged"];
    if (a.quiet === "shelved") parts.push("shelved until " + when(a.shelved_until));
    else if (a.quiet === "chattering") parts.push("chattering: not announced again for now");
    else if (a.quiet === "flood") parts.push("held by the flood");
    return parts.join(", ");
  }

  function drawPanel() {
    const rows = A.alerts.slice().sort((x, y) =>
      (x.acked - y.acked) || LEVEL_RANK[levelOf(y)] - LEVEL_RANK[levelOf(x)] || (y.last || 0) - (x.last || 0));
    A.rows.replaceChildren(...(rows.length ? rows.map(panelRow) : [el("li", "empty", "no alarm")]));
  }

  function panelRow(a) {
    const li = el("li", "alarm");
    li.dataset.alertId = String(a.id);
    li.dataset.level = levelOf(a);
    li.dataset.station = a.station || "";
    li.dataset.state = a.quiet || (a.acked ? "acked" : "open");
    li.append(el("span", "alert-level", levelOf(a).toUpperCase()));
    const body = el("span", "alarm-body");
    body.append(el("span", "alert-text", a.text));
    const count = Number.isInteger(a.count) && a.count > 1 ? a.count + " times, " : "";
    body.append(el("span", "alarm-meta",
      (a.station ? "station " + a.station + " · " : "") + count + "first " + when(a.raised) +
      (a.count > 1 ? ", last " + when(a.last) : "") + " · " + stateOf(a)));
    li.append(body);
    if (!a.acked) li.append(button("Acknowledge", "alert-ack", "", () => ack(a.id, a.station)));
    if (!a.station) {
      if (a.quiet === "shelved") {
        li.append(button("Unshelve", "alarm-unshelve", "announce it again when it comes back", () => shelve(a, 0)));
      } else if (a.level !== "advisory") {
        li.append(button("Shelve 10 min", "alarm-shelve", "not announced for 10 minutes", () => shelve(a, 600)));
        li.append(button("Shelve 1 h", "alarm-shelve", "not announced for an hour", () => shelve(a, 3600)));
      }
    }
    return li;
  }

  async function post(path, body) {
    let r;
    try {
      r = await window.gcsToken.fetch(path, {
        method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
      });
    } catch (err) {
      return "the station did not answer";
    }
    if (r.ok) return null;
    let why = "HTTP " + r.status;
    try { why = (await r.json()).error || why; } catch (err) { /* not JSON */ }
    return why;
  }

  async function ack(id, station) {
    A.hidden.add(key(id, station));
    draw();
    const why = await post("/api/alerts/ack", station ? { id, station } : { id });
    A.note.textContent = A.pnote.textContent = why ? "acknowledgement refused: " + why : "";
    if (why) {
      A.hidden.delete(key(id, station));
      draw();
    }
  }

  async function shelve(a, seconds) {
    const what = seconds ? "Shelve for " + Math.round(seconds / 60) + " min (not announced, still listed)" : "Unshelve";
    if (seconds && !window.confirm(what + ": " + a.text + "?")) return;
    const why = await post("/api/alerts/shelve", { id: a.id, seconds });
    A.pnote.textContent = why ? "not shelved: " + why : "";
  }

  function onState(st) {
    if (!st || !Array.isArray(st.alerts)) return;  // a push without alerts keeps the last ones
    if (st.station && typeof st.station.name === "string") A.here = st.station.name;
    // each alert's station: another station's name, or "" (this station's own)
    A.alerts = st.alerts.filter(valid).map((a) => ({ ...a, station: remote(a) || "" }));
    A.rate = st.alarm_rate && typeof st.alarm_rate === "object" ? st.alarm_rate : null;
    const ids = new Set(A.alerts.map((a) => key(a.id, a.station)));
    for (const k of A.hidden) if (!ids.has(k)) A.hidden.delete(k);
    // sound: criticals announced since the page last looked (none for the first state)
    const first = A.heard === null;
    if (first) A.heard = new Map();
    for (const a of A.alerts) {
      const k = key(a.id, a.station), t = a.announced;
      if (typeof t !== "number" || A.heard.get(k) === t) continue;
      A.heard.set(k, t);
      if (!first && a.level === "critical" && inBanner(a)) sound(a);
    }
    draw();
  }

  window.gcsStateHooks = window.gcsStateHooks || [];
  window.gcsStateHooks.push(onState);
  window.gcsAlerts = Object.freeze({
    get open() { return visible().map((a) => a.id); },
    get openByStation() { return visible().map((a) => ({ id: a.id, station: a.station })); },
    get sounded() { return A.sounded; },
    get spoken() { return A.spoken.slice(); },
    get sound() { return soundOn(); },
    ack,
    shelve,
  });
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", draw);
  else draw();
})();
