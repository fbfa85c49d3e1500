// Application keys on the dashboard: a client (Cura's OctoPrint connection) that asks
// for a key of its own shows up here with its name and address, to allow or deny; the
// keys given are listed with a Revoke button. Uses app.js's api(), esc() and notice().
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
  const pending = view.pending.filter((r) => r.decision === "pending");
  section.hidden = pending.length === 0 && view.keys.length === 0;
  const rows = pending.map((r) =>
    '<li class="appkey-request" data-id="' + esc(r.id) + '"><b>' + esc(r.app) +
    "</b> asks for a key, from " + esc(r.source) + " on " + esc(r.instance) +
    ' <button type="button" data-act="allow">Allow</button>' +
    ' <button type="button" data-act="deny">Deny</button></li>');
  const keys = view.keys.map((k) =>
    '<li class="appkey" data-id="' + esc(k.id) + '">' + esc(k.app) + " (from " + esc(k.source) +
    ", key " + esc(k.id) + ') <button type="button" data-act="revoke">Revoke</button></li>');
  const html = "<ul>" + rows.join("") + keys.join("") + "</ul>";
  if (section.dataset.html !== html) {
    section.dataset.html = html;
    document.querySelector("#appkeylist").innerHTML = html;
  }
}

document.querySelector("#appkeylist").addEventListener("click", async (e) => {
  const act = e.target.dataset && e.target.dataset.act;
  if (!act) return;
  const id = e.target.closest("li").dataset.id;
  const path = act === "revoke"
    ? "/api/v1/appkeys/keys/" + encodeURIComponent(id) + "/revoke"
    : "/api/v1/appkeys/requests/" + encodeURIComponent(id) + "/" + act;
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
