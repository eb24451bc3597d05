/* Ground station page: the state deltas the station's WebSocket pushes.
 *
 * Theory of operation
 * -------------------
 * The socket sends the whole state once ({"type":"state","seq":N,...}), then at each
 * push only what changed ({"type":"delta","seq":N+1,"base":N,...}); the format is
 * written down in the station's swarm/core/station/delta.py, which this file
 * mirrors. window.gcsDelta.next(model, seq, delta) gives the new state, or null when
 * the delta does not follow the state the page holds (a gap in the sequence, no
 * state yet, or an edit that does not fit): the page then asks for the whole state
 * ({"type":"state"}) and ignores deltas until it arrives. The state it returns is a
 * new object (agents patched are new objects, the others are shared), so the
 * drawing code sees what changed by identity.
 */
(function () {
  "use strict";

  function misfit(what) {
    const e = new Error("delta does not fit: " + what);
    e.misfit = true;
    throw e;
  }

  // [cut, keep, added...]: old.slice(cut, cut + keep) then added (0 in a trail: the agent's [lat, lon])
  function editList(old, edit, here, what) {
    if (!Array.isArray(edit) || edit.length < 2) misfit(what);
    const cut = edit[0], keep = edit[1];
    const base = Array.isArray(old) ? old : [];
    if (!Number.isInteger(cut) || !Number.isInteger(keep) || cut < 0 || keep < 0 || cut + keep > base.length) {
      misfit(what);
    }
    const added = edit.slice(2);
    if (here) for (let i = 0; i < added.length; i++) if (added[i] === 0) added[i] = here.slice();
    return base.slice(cut, cut + keep).concat(added);
  }

  function patchAgent(old, p, id) {
    if (!p || typeof p !== "object" || (!old && p.id !== id)) misfit("agent " + id);
    const a = Object.assign({}, old || {});
    if (Array.isArray(p.unset)) for (const k of p.unset) delete a[k];
    for (const k of Object.keys(p)) if (k !== "unset" && k !== "trail") a[k] = p[k];
    if (p.trail !== undefined) {
      a.trail = editList(old ? old.trail : [], p.trail, [a.lat, a.lon], "agent " + id + " trail");
    }
    return a;
  }

  // an alarm's key: "<station>:<id>" (the station empty for this station's own)
  function alertKey(a) {
    return (a && a.station ? a.station : "") + ":" + (a ? a.id : undefined);
  }

  // the alarms' part: {set: {key: patch}, drop: [key], order: [key]}
  function applyAlerts(old, e) {
    if (!e || typeof e !== "object" || Array.isArray(e)) misfit("alerts");
    const items = new Map();
    for (const a of Array.isArray(old) ? old : []) items.set(alertKey(a), a);
    for (const k of Array.isArray(e.drop) ? e.drop : []) if (!items.delete(k)) misfit("alert " + k);
    if (e.set !== undefined) {
      if (!e.set || typeof e.set !== "object" || Array.isArray(e.set)) misfit("alerts set");
      for (const k of Object.keys(e.set)) {
        const p = e.set[k], base = items.get(k);
        if (!p || typeof p !== "object" || (!base && alertKey(p) !== k)) misfit("alert " + k);
        const a = Object.assign({}, base || {});
        if (Array.isArray(p.unset)) for (const f of p.unset) delete a[f];
        for (const f of Object.keys(p)) if (f !== "unset") a[f] = p[f];
        items.set(k, a);
      }
    }
    const keys = Array.isArray(e.order) ? e.order : Array.from(items.keys());
    if (keys.length !== items.size || keys.some((k) => !items.has(k))) misfit("alerts order");
    return keys.map((k) => items.get(k));
  }

  function apply(old, d) {
    const st = Object.assign({}, old);
    if (Array.isArray(d.unset)) for (const k of d.unset) delete st[k];
    if (d.set && typeof d.set === "object") Object.assign(st, d.set);
    if (d.events !== undefined) st.events = editList(old.events, d.events, null, "events");
    if (d.alerts !== undefined) st.alerts = applyAlerts(old.alerts, d.alerts);
    const agents = new Map();
    for (const a of Array.isArray(old.agents) ? old.agents : []) agents.set(a.id, a);
    for (const id of Array.isArray(d.drop) ? d.drop : []) if (!agents.delete(id)) misfit("drop " + id);
    if (d.agents !== undefined) {
      if (!d.agents || typeof d.agents !== "object" || Array.isArray(d.agents)) misfit("agents");
      for (const key of Object.keys(d.agents)) {
        if (!/^[0-9]{1,9}$/.test(key)) misfit("agent " + key);
        const id = Number(key);
        agents.set(id, patchAgent(agents.get(id), d.agents[key], id));
      }
    }
    const ids = Array.isArray(d.order) ? d.order : Array.from(agents.keys()).sort((x, y) => x - y);
    if (ids.length !== agents.size || ids.some((i) => !agents.has(i))) misfit("order");
    st.agents = ids.map((i) => agents.get(i));
    return st;
  }

  // for tests: the newest state built from a delta, and how many were applied
  const seen = { last: null, applied: 0, refused: 0 };

  function next(model, seq, d) {
    if (!model || typeof seq !== "number" || d.base !== seq || d.seq !== seq + 1) {
      seen.refused += 1;
      return null;
    }
    try {
      const st = apply(model, d);
      st.seq = d.seq;
      seen.last = st;
      seen.applied += 1;
      return st;
    } catch (err) {
      if (err && err.misfit) {
        seen.refused += 1;
        return null;
      }
      throw err;
    }
  }

  window.gcsDelta = Object.freeze({
    apply,
    next,
    get last() { return seen.last; },
    get applied() { return seen.applied; },
    get refused() { return seen.refused; },
  });
})();
