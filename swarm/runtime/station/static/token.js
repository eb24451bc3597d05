/* Ground station page: the station's token (docs/security.md, "The ground station's API").
 *
 * Theory of operation
 * -------------------
 * A station beyond loopback (or started with --token) answers its API only with its
 * token. The operator opens the address the station printed, /?token=...; this
 * script, the first the page runs, takes the token from the address, keeps it in
 * the page's localStorage and removes it from the address bar at once
 * (history.replaceState: not in the history, a bookmark or a copied link).
 * localStorage belongs to the page's origin (scheme, host and port): no other web
 * service of the machine can read it, where a cookie would have been sent to all of
 * them (cookies are per host, whatever the port). A reload, or a new tab of the same
 * address, finds it there.
 *
 * window.gcsToken.fetch(url, options) is fetch with "Authorization: Bearer TOKEN"
 * added; window.gcsToken.protocols() are the WebSocket subprotocols to offer:
 * "swarm-gcs" (the station answers with it) and "token.TOKEN" (a browser cannot put
 * a header on a WebSocket). When the station refuses the token (a station restarted
 * with a new one) or there is none, window.gcsToken.ask() shows the form in the page
 * (#token-needed): it opens /?token=... as the printed address does.
 */
(function () {
  "use strict";

  const KEY = "gcs_token";
  const RULE = /^[A-Za-z0-9._~-]{16,256}$/;  // security.py's TOKEN_RULE
  let token = null;
  try {
    token = window.localStorage.getItem(KEY);
  } catch (err) {
    token = null;  // storage disabled: the token lives as long as the page
  }
  if (token !== null && !RULE.test(token)) token = null;

  const u = new URL(location.href);
  if (u.searchParams.has("token")) {
    const given = u.searchParams.get("token") || "";
    u.searchParams.delete("token");
    history.replaceState(history.state, "", u.pathname + u.search + u.hash);
    if (RULE.test(given)) {
      token = given;
      try {
        window.localStorage.setItem(KEY, given);
      } catch (err) { /* kept for this page only */ }
    }
  }

  function withToken(headers) {
    const h = new Headers(headers || {});
    if (token !== null) h.set("Authorization", "Bearer " + token);
    return h;
  }

  function ask() {
    const box = document.getElementById("token-needed");
    if (!box || !box.hidden) return;
    box.hidden = false;
    const input = box.querySelector("input[name=token]");
    if (input) input.focus();
  }

  window.gcsToken = Object.freeze({
    get present() { return token !== null; },
    fetch(url, options) {
      const o = Object.assign({}, options || {});
      o.headers = withToken(o.headers);
      return fetch(url, o);
    },
    protocols() {
      return token !== null ? ["swarm-gcs", "token." + token] : ["swarm-gcs"];
    },
    ask,
  });
})();
