/* Ground station page: several swarms as groups (issue 16).
 *
 * Theory of operation
 * -------------------
 * The station's state names its swarms: "swarms" is a list of {leader, members,
 * colour} (a swarm is a leader and the agents that follow it; its colour a small
 * integer the station keeps while the swarm lives; with stations joined over Zenoh,
 * each also has its "station" and the colour is the merged view's, the same on every
 * station's page and one per swarm: swarm.core.station.swarms.fleet_colours). The
 * first 8 colours are PALETTE's (the station's rule knows its size), beyond it the
 * page makes one per index. This file reads that list at
 * every state (window.gcsStateHooks) and, once app.js has drawn it
 * (window.gcsDrawHooks), shows the swarms as groups:
 *
 * - with two swarms or more, every agent takes its swarm's colour (marker, trail,
 *   table row: app.js asks window.gcsSwarms.colour(id)); each swarm's leader keeps
 *   the leader's gold mark and "L"; an agent in no swarm is drawn white. With one
 *   swarm the page looks as it always did (a colour per agent);
 * - the fleet table has a "swarm" column (the leader's name, and the agent's radio
 *   network "net" when the station reports one) and is sorted by swarm, leader first,
 *   by default (the column's header sorts by it again); "show" filters the table to
 *   one swarm;
 * - another station's swarm (one joined over Zenoh) is named "at station NAME" in the
 *   selectors and confirmations, and its agents' swarm cell says "station NAME";
 * - the commands' "to" selector offers "all swarms" and each swarm by its leader
 *   ({"target": "swarm", "swarm": <leader id>}); the confirmation names the swarm(s)
 *   and how many agents. A follow in V to every swarm is refused here, as the station
 *   refuses it: several swarms sent the same way from near each other would meet.
 *
 * Hooks for tests: #agents tr[data-swarm], td[data-field="swarm"], #swarm-filter,
 * #swarm-summary, window.gcsSwarms.list().
 */
(function () {
  "use strict";

  // one colour per swarm: no red (alerts), yellow (the leader's mark) or grey (stale)
  const PALETTE = ["#4e9bff", "#ff9a3c", "#6fd35a", "#c17dff", "#3fd0c9", "#ff7fc4", "#b6e05a", "#8fa8ff"];
  const NO_SWARM = "#f2f2f2";  // an agent in no swarm while there are several
  const M = { swarms: [], of: new Map(), byLeader: new Map(), state: null, options: "" };

  function swarmList(st) {
    const list = st && Array.isArray(st.swarms) ? st.swarms : [];
    return list.filter((s) => s && Number.isInteger(s.leader) && Array.isArray(s.members));
  }
  function onState(st) {
    M.state = st;
    M.swarms = swarmList(st);
    M.of = new Map();
    M.byLeader = new Map();
    for (const s of M.swarms) {
      M.byLeader.set(s.leader, s);
      for (const id of s.members) M.of.set(id, s);
    }
  }
  const several = () => M.swarms.length > 1;
  // the station's colour index: the palette's, beyond it one made for it (a hue turned by the
  // golden angle, kept out of red and yellow), so every swarm shown has its own
  function paletteColour(s) {
    const i = Number.isInteger(s.colour) && s.colour >= 0 ? s.colour : 0;
    if (i < PALETTE.length) return PALETTE[i];
    const hue = 70 + ((i - PALETTE.length) * 137.508) % 260;  // 70..330: no red, no yellow
    const light = [62, 74, 52][(i - PALETTE.length) % 3];
    return "hsl(" + hue.toFixed(1) + ", 75%, " + light + "%)";
  }
  function agentName(id) {
    return window.gcs ? window.gcs.agentName(id) : "agent " + id;
  }
  function connectedCount(ids) {
    const st = window.gcs && window.gcs.state;
    const up = new Set((st && Array.isArray(st.agents) ? st.agents : []).filter((a) => a.connected).map((a) => a.id));
    return ids ? ids.filter((id) => up.has(id)).length : up.size;
  }
  function agents(n) {
    return n === 1 ? "1 agent" : n + " agents";
  }
  // another station's swarm: " at station NAME" (its commands go through that station)
  function where(s) {
    const st = M.state && M.state.station ? M.state.station.name : null;
    return s && typeof s.station === "string" && s.station !== st ? " at station " + s.station.slice(0, 32) : "";
  }
  function swarmName(leader) {
    return "the swarm of " + agentName(leader) + where(M.byLeader.get(leader));
  }

  // ------------------------------------------------------------ app.js asks
  window.gcsSwarms = Object.freeze({
    list() { return M.swarms.map((s) => ({ leader: s.leader, members: s.members.slice(), colour: s.colour })); },
    leaders(st) { return new Set(swarmList(st).map((s) => s.leader)); },
    // the agent's colour: its swarm's while there are several; null: its own (app.js's)
    colour(id) {
      if (!several()) return null;
      const s = M.of.get(id);
      return s ? paletteColour(s) : NO_SWARM;
    },
    // the fleet table's grouping: by swarm (by leader id), the leader first; no swarm last
    sortKey(id) {
      if (!several()) return null;
      const s = M.of.get(id);
      return s ? s.leader * 2 + (s.leader === id ? 0 : 1) : 1000;
    },
    refusal(cmd) {
      if (cmd.target !== "swarm" || cmd.kind !== "follow" || cmd.swarm !== undefined || !several()) return null;
      return "follow: " + M.swarms.length + " swarms sent the same way would meet: choose one swarm in \"to\"";
    },
    addressees(cmd) {
      if (cmd.swarm !== undefined) {
        const s = M.byLeader.get(cmd.swarm);
        if (cmd.kind === "follow") return swarmName(cmd.swarm) + " (through its leader)";
        return swarmName(cmd.swarm) + ": " + agents(connectedCount(s ? s.members : []));
      }
      if (!several()) return null;
      return "every swarm (" + M.swarms.length + " swarms, " + agents(connectedCount(null)) + ")";
    },
    name(cmd) {
      if (cmd.swarm !== undefined) return swarmName(cmd.swarm);
      return several() ? "every swarm" : "swarm";
    },
    toText(value) {
      const lead = value.startsWith("swarm:") ? Number(value.slice(6)) : null;
      if (lead !== null) {
        const s = M.byLeader.get(lead);
        return "→ " + swarmName(lead) + ": " + agents(connectedCount(s ? s.members : []));
      }
      return several() ? "every swarm (" + M.swarms.length + ")" : "every agent";
    },
  });

  // ------------------------------------------------------------ the fleet table
  function swarmCell(row) {
    let td = row.querySelector('td[data-field="swarm"]');
    if (!td) {
      td = document.createElement("td");
      td.dataset.field = "swarm";
      const role = row.querySelector('td[data-field="role"]');
      if (role) role.after(td); else row.append(td);
    }
    return td;
  }
  function drawRows(st) {
    const byId = new Map((Array.isArray(st.agents) ? st.agents : []).map((a) => [a.id, a]));
    const show = document.querySelector("#swarm-filter").value;
    for (const row of document.querySelectorAll("#agents tbody tr[data-agent-id]")) {
      const id = Number(row.dataset.agentId);
      const s = M.of.get(id);
      const a = byId.get(id);
      let net = a && a.net !== undefined && a.net !== null ? " · net " + String(a.net).slice(0, 24) : "";
      const here = st.station ? st.station.name : null;
      if (a && typeof a.station === "string" && a.station !== here) net += " · station " + a.station.slice(0, 32);
      const text = (s ? (s.leader === id ? "leads" : agentName(s.leader)) : "—") + net;
      const td = swarmCell(row);
      if (td.textContent !== text) td.textContent = text;
      const key = s ? String(s.leader) : "";
      if (row.dataset.swarm !== key) row.dataset.swarm = key;
      row.hidden = show !== "all" && key !== show;
    }
  }
  function drawChoices() {
    const key = M.swarms.map((s) => s.leader + ":" + s.members.length + where(s)).join(",") + "|" + several();
    if (key === M.options) return;
    M.options = key;
    const target = document.querySelector("#cmd-target");
    const filter = document.querySelector("#swarm-filter");
    const keepTarget = target.value;
    const keepFilter = filter.value;
    for (const o of Array.from(target.options)) if (o.value.startsWith("swarm:")) o.remove();
    const all = Array.from(target.options).find((o) => o.value === "swarm");
    if (all) all.textContent = several() ? "all swarms" : "whole swarm";
    filter.replaceChildren(new Option("all swarms", "all"));
    for (const s of M.swarms) {
      const label = "swarm of " + agentName(s.leader) + where(s) + " · " + agents(s.members.length);
      if (several()) target.add(new Option(label, "swarm:" + s.leader));
      filter.add(new Option(label, String(s.leader)));
    }
    // a swarm that is gone is no longer chosen (the station would refuse it anyway)
    target.value = Array.from(target.options).some((o) => o.value === keepTarget) ? keepTarget : "selected";
    filter.value = Array.from(filter.options).some((o) => o.value === keepFilter) ? keepFilter : "all";
    document.querySelector("#swarm-show").hidden = M.swarms.length < 2 && filter.value === "all";
    if (window.gcs) window.gcs.drawTarget();
  }
  function drawSummary() {
    const el = document.querySelector("#swarm-summary");
    el.hidden = !several();
    const text = M.swarms.length + " swarms: " + M.swarms.map((s) => agentName(s.leader) + " " + s.members.length).join(", ");
    if (el.textContent !== text) el.textContent = text;
  }
  function onDraw(st) {
    if (st !== M.state) onState(st);
    drawChoices();
    drawRows(st);
    drawSummary();
  }

  (window.gcsStateHooks = window.gcsStateHooks || []).push(onState);
  (window.gcsDrawHooks = window.gcsDrawHooks || []).push(onDraw);
  document.querySelector("#swarm-filter").addEventListener("change", () => {
    if (M.state) drawRows(M.state);
  });
})();
