// The preference study page: one rater session per browser (the id lives in localStorage), one
// trial at a time; the server decides the order and which model is A, and never names them.
"use strict";
const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
window.dojoStudy = { rater: null, trial: null, stored: 0, done: false, errors: [] };

let trial = null;

function log(text) { $("log").textContent = text; if (text) window.dojoStudy.errors.push(text); }

async function api(path, body) {
  const r = await fetch(path, body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  const json = await r.json();
  if (!r.ok) { const e = new Error(json.error || r.statusText); e.status = r.status; throw e; }
  return json;
}

async function rater() {
  const key = "dojo-study-rater:" + location.host;
  let id = params.get("rater") || localStorage.getItem(key);
  if (!id) {
    id = (await api("/api/study/raters", {})).rater;
    localStorage.setItem(key, id);
  }
  window.dojoStudy.rater = id;
  return id;
}

function replay() {
  for (const v of ["truth", "left", "right"]) { $(v).currentTime = 0; $(v).play().catch(() => {}); }
}

function answers() {
  const out = {};
  for (const q of trial.questions) {
    const picked = document.querySelector(`input[name="${q.id}"]:checked`);
    if (!picked) return null;
    out[q.id] = picked.value;
  }
  return out;
}

async function next() {
  let id = await rater();
  let t;
  try {
    t = await api("/api/study/next?rater=" + encodeURIComponent(id));
  } catch (e) {
    // Only a rater id this study does not know (another study, a new vote database) starts a new
    // rater session; a network error or a restarting server must not count one person twice.
    if (!(e.status === 400 && /unknown rater/.test(e.message))) throw e;
    localStorage.removeItem("dojo-study-rater:" + location.host);
    id = await rater();
    t = await api("/api/study/next?rater=" + encodeURIComponent(id));
  }
  $("progress").textContent = `${t.progress.answered} of ${t.progress.total} done`;
  if (t.done) {
    window.dojoStudy.done = true;
    document.querySelector(".videos").hidden = true;
    $("questions").innerHTML = "<p>All done: thank you.</p>";
    $("submit").hidden = true;
    return;
  }
  trial = t;
  window.dojoStudy.trial = t.trial;
  for (const v of ["truth", "left", "right"]) $(v).src = t[v];
  const form = $("questions");
  form.innerHTML = "";
  for (const q of t.questions) {
    const set = document.createElement("fieldset");
    set.innerHTML = `<legend></legend>`;
    set.querySelector("legend").textContent = q.text;
    for (const [value, text] of [["left", "A"], ["right", "B"], ["tie", "tie"]]) {
      const label = document.createElement("label");
      label.innerHTML = `<input type="radio" name="${q.id}" value="${value}"> ${text}`;
      set.appendChild(label);
    }
    form.appendChild(set);
  }
  $("submit").disabled = true;
  replay();
}

$("questions").addEventListener("change", () => { $("submit").disabled = !trial || !answers(); });
$("replay").addEventListener("click", replay);
$("submit").addEventListener("click", async () => {
  const a = answers();
  if (!a) return;
  $("submit").disabled = true;
  try {
    await api("/api/study/vote", { rater: window.dojoStudy.rater, trial: trial.trial, answers: a });
    window.dojoStudy.stored += 1;
    log("");
    await next();
  } catch (e) {
    if (e.status === 409) { log(""); await next(); return; }  // stored before; the reply was lost
    log(e.message);
    $("submit").disabled = false;
  }
});

next().catch((e) => log(e.message));
