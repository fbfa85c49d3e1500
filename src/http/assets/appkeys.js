// Application keys on the dashboard: a client (Cura's OctoPrint connection) that asks
// for a key of its own shows up here with its name, address and instance, to allow or
// deny. Allowing chooses the key's scope: upload only (Allow) or upload and control of
// prints (Allow with control), on the instance it asked on or, ticked, everywhere. The
// keys given are listed with their scope, buttons to change it, and Revoke. Uses app.js's
// api(), esc() and notice().
"use strict";

async function refreshAppKeys() {
  const section = document.querySelector("#appkeys");
  let view;
  try {
    view = await (await fetch("/api/v1/appkeys", { headers: headers() })).json();
  } catch (_) {
    return;
  }
  if (!view || !Array.isArray(view.pending)) return;
  // Decided requests leave the list at once; older daemons kept them marked.
  const pending = view.pending.filter((r) => r.decision === "pending");
  section.hidden = pending.length === 0 && view.keys.length === 0;
  const rows = pending.map((r) =>
    '<li class="appkey-request" data-id="' + esc(r.id) + '"><b>' + esc(r.app) +
    "</b> asks for a key, from " + esc(r.source) + " on " + esc(r.instance) +
    ' <button type="button" data-act="allow" title="upload and print its own uploads">Allow</button>' +
    ' <button type="button" data-act="allow-control" title="also pause, resume and cancel prints">Allow with control</button>' +
    ' <label title="every OctoPrint instance of the farm, not only ' + esc(r.instance) +
    '"><input type="checkbox" class="everywhere"> everywhere</label>' +
    ' <button type="button" data-act="deny">Deny</button></li>');
  const keys = view.keys.map((k) => {
    const scope = k.scope || {};
    return '<li class="appkey" data-id="' + esc(k.id) + '" data-control="' + (scope.control ? "1" : "") +
      '" data-everywhere="' + (scope.everywhere ? "1" : "") + '">' + esc(k.app) +
      " (from " + esc(k.source) + ", key " + esc(k.id) + "): " +
      '<span class="appkey-scope">' + esc(k.scope_text || k.instance) + "</span>" +
      ' <button type="button" data-act="toggle-control">' +
      (scope.control ? "Upload only" : "Give control") + "</button>" +
      ' <button type="button" data-act="toggle-everywhere">' +
      (scope.everywhere ? "Own instance only" : "Everywhere") + "</button>" +
      ' <button type="button" data-act="revoke">Revoke</button></li>';
  });
  const html = "<ul>" + rows.join("") + keys.join("") + "</ul>";
  if (section.dataset.html !== html) {
    section.dataset.html = html;
    document.querySelector("#appkeylist").innerHTML = html;
  }
}

document.querySelector("#appkeylist").addEventListener("click", async (e) => {
  const act = e.target.dataset && e.target.dataset.act;
  if (!act) return;
  const item = e.target.closest("li");
  const id = encodeURIComponent(item.dataset.id);
  const scope = (control, everywhere) =>
    "?control=" + (control ? "true" : "false") + "&everywhere=" + (everywhere ? "true" : "false");
  let path;
  if (act === "revoke") {
    path = "/api/v1/appkeys/keys/" + id + "/revoke";
  } else if (act === "deny") {
    path = "/api/v1/appkeys/requests/" + id + "/deny";
  } else if (act === "allow" || act === "allow-control") {
    const everywhere = item.querySelector("input.everywhere").checked;
    path = "/api/v1/appkeys/requests/" + id + "/allow" + scope(act === "allow-control", everywhere);
  } else if (act === "toggle-control" || act === "toggle-everywhere") {
    let control = item.dataset.control === "1";
    let everywhere = item.dataset.everywhere === "1";
    if (act === "toggle-control") control = !control;
    else everywhere = !everywhere;
    path = "/api/v1/appkeys/keys/" + id + "/allow" + scope(control, everywhere);
  } else {
    return;
  }
  try {
    const answer = await api("POST", path);
    notice(answer.message || "done");
  } catch (err) {
    notice(err.message, true);
  }
  refreshAppKeys();
});

refreshAppKeys();
setInterval(refreshAppKeys, 2000);
