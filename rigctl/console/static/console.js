// rigctl console: the live parts (the service's event stream) and the actions (its JSON
// API). The bearer token stays in this browser session only (sessionStorage); giving it
// also signs in (/console/login: a session cookie, for the pages when reads need it).
"use strict";

const TOKEN_KEY = "rigctl-token";

function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }

function showMessage(text, kind) {
  const box = document.getElementById("message");
  box.textContent = text;
  box.className = kind || "error";
  box.hidden = !text;
}

function detailText(data, status) {
  // FastAPI answers {"detail": "..."} or {"detail": [{"loc": [...], "msg": "..."}]}
  const detail = data && data.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map(e => (e.loc || []).join(".") + ": " + e.msg).join("\n");
  }
  return "HTTP " + status;
}

async function post(url, body) {
  const headers = { "Content-Type": "application/json" };
  if (token()) headers.Authorization = "Bearer " + token();
  const response = await fetch(url, { method: "POST", headers, body: JSON.stringify(body || {}) });
  let data = null;
  try { data = await response.json(); } catch (e) { data = null; }
  if (!response.ok) {
    let text = "refused (" + response.status + "): " + detailText(data, response.status);
    if (response.status === 401) text += "\nEnter the service's bearer token above.";
    showMessage(text, "error");
    if (response.status === 401) document.getElementById("token").focus();
  }
  return { ok: response.ok, status: response.status, data };
}

function setupToken() {
  const form = document.getElementById("token-form");
  const state = document.getElementById("token-state");
  const show = () => { state.textContent = token() ? " set" : ""; };
  show();
  form.addEventListener("submit", ev => {
    ev.preventDefault();
    const value = document.getElementById("token").value.trim();
    if (value) sessionStorage.setItem(TOKEN_KEY, value); else sessionStorage.removeItem(TOKEN_KEY);
    document.getElementById("token").value = "";
    show();
    const body = new URLSearchParams({ token: value, next: "/console/" });
    fetch(value ? "/console/login" : "/console/logout", { method: "POST", body, redirect: "manual" })
      .catch(() => {});
  });
}

function markNav() {
  const path = location.pathname;
  const current = path.startsWith("/console/runs") ? "runs"
    : path.startsWith("/console/history") ? "history"
    : path.startsWith("/console/start") ? "start" : "rig";
  document.querySelectorAll("[data-nav]").forEach(a => {
    if (a.dataset.nav === current) a.classList.add("active");
  });
}

// aborts: any button with data-abort (also in fragments loaded later)
document.addEventListener("click", async ev => {
  const button = ev.target.closest("[data-abort]");
  if (!button) return;
  const runId = button.dataset.abort;
  if (!confirm("Abort run " + runId + "?")) return;
  const r = await post("/runs/" + encodeURIComponent(runId) + "/abort",
                       { operator: sessionStorage.getItem("rigctl-operator") || null });
  if (r.ok) showMessage("run " + runId + ": " + r.data.status, "info");
});

// resumes: any button with data-resume (a stopped or paused run)
document.addEventListener("click", async ev => {
  const button = ev.target.closest("[data-resume]");
  if (!button) return;
  const runId = button.dataset.resume;
  const r = await post("/runs/" + encodeURIComponent(runId) + "/resume",
                       { operator: sessionStorage.getItem("rigctl-operator") || null });
  if (r.ok) showMessage("run " + runId + ": " + (r.data.status || "resuming"), "info");
});

function setupCurate() {
  const form = document.getElementById("curate-form");
  if (!form) return;
  form.addEventListener("submit", async ev => {
    ev.preventDefault();
    const exclude = [...document.querySelectorAll("input[name=exclude]:checked")]
      .map(el => Number(el.value));
    if (!exclude.length) { showMessage("check the captures to leave out first", "error"); return; }
    showMessage("solving again without " + exclude.join(", ") + " ...", "info");
    const r = await post("/runs/" + encodeURIComponent(form.dataset.run) + "/solve",
                         { exclude, reason: form.elements.reason.value,
                           operator: sessionStorage.getItem("rigctl-operator") || null });
    if (r.ok) location.reload();
  });
}

function setupTeach() {
  const box = document.getElementById("teach");
  if (!box) return;
  const press = async action => {
    const r = await post("/runs/" + encodeURIComponent(box.dataset.run) + "/teach", { action });
    if (!r.ok) return;
    document.getElementById("teach-count").textContent = r.data.captures;
    const report = r.data.pose_set;
    if (report) {
      const text = document.getElementById("teach-report");
      text.textContent = report.note;
      text.className = report.warning ? "error" : "ok-text";
    }
    showMessage(action === "done" ? "teaching done: solving"
                : "captured " + String(r.data.index).padStart(3, "0"), "info");
  };
  document.getElementById("teach-capture").addEventListener("click", () => press("capture"));
  document.getElementById("teach-done").addEventListener("click", () => press("done"));
}

function setupPreview() {
  const img = document.getElementById("preview");
  if (!img) return;
  const every = Number(img.dataset.refreshMs) || 3000;
  setInterval(() => {
    if (document.hidden) return;
    const next = new Image();
    next.onload = () => { img.src = next.src; };
    next.src = "/console/preview.jpg?t=" + Date.now();
  }, every);
}

async function refreshLive() {
  for (const el of document.querySelectorAll("[data-live]")) {
    const response = await fetch(el.dataset.live);
    if (response.ok) swapChanged(el, await response.text());
  }
}

// Only the parts of a live fragment that changed are replaced (its sections, by id): a
// replaced button is a new element, and a click whose press and release straddle the
// swap is lost. The current run's progress changes at every step; the queue's abort
// buttons beside it stay the same elements until the queue changes.
function swapChanged(el, html) {
  const fresh = document.createElement("template");
  fresh.innerHTML = html;
  const parts = [...fresh.content.children];
  const old = [...el.children];
  const bare = [...fresh.content.childNodes].some(
    n => n.nodeType !== Node.ELEMENT_NODE && n.textContent.trim());
  const sameLayout = !bare && parts.length > 0 && parts.length === old.length
    && parts.every((part, i) => part.id && part.id === old[i].id);
  if (!sameLayout) {
    el.innerHTML = html;
    return;
  }
  parts.forEach((part, i) => {
    if (part.outerHTML !== old[i].outerHTML) old[i].replaceWith(part);
  });
}

function onProgress(event) {
  const bar = document.getElementById("progress");
  if (bar && (!bar.dataset.run || bar.dataset.run === event.run_id)) {
    bar.max = event.total || 1;
    bar.value = event.index || 0;
    const text = document.getElementById("progress-text");
    if (text) text.textContent = "step " + event.index + "/" + event.total + ": " + event.step;
  }
}

function subscribe(handlers) {
  const source = new EventSource("/events");
  for (const [type, handler] of Object.entries(handlers)) {
    source.addEventListener(type, ev => handler(JSON.parse(ev.data)));
  }
  return source;
}

// The runner announces "finished" before it releases the rig's lock and before the
// service drops the run as current (and, for a calibration, records its decision): a
// refresh on that event alone can show the finished run still running. So refresh until
// the run is gone from the live section (a few tries a little apart).
const SETTLE_TRIES = 40, SETTLE_MS = 250;

async function refreshUntilGone(runId, tries) {
  await refreshLive();
  const link = document.querySelector("#current-run a");
  const still = link && link.getAttribute("href") === "/console/runs/" + runId;
  const busy = document.querySelector("#rig-state .badge.running");
  if ((still || (busy && !link)) && tries > 0) {
    setTimeout(() => refreshUntilGone(runId, tries - 1), SETTLE_MS);
  }
}

function setupLive() {
  const live = document.querySelector("[data-live]");
  // the run's progress bar, or (a calibration that ended) the mark that its decision is due
  const runBar = document.querySelector("progress[data-run]")
    || document.getElementById("awaiting-decision");
  if (!live && !runBar) return;
  const mine = e => runBar && runBar.dataset.run === e.run_id;
  const source = subscribe({
    step: e => { if (live && !document.getElementById("progress")) refreshLive(); onProgress(e); },
    queued: () => refreshLive(),
    started: e => {
      refreshLive();
      if (mine(e) && "queued" in runBar.dataset) location.reload();  // now it has a record
    },
    finished: e => {
      if (live) refreshUntilGone(e.run_id, SETTLE_TRIES);
      // a calibration that succeeded gets its decision next: reload on that
      if (mine(e) && !(e.status === "succeeded" && "calibration" in runBar.dataset)) {
        location.reload();
      }
    },
    decision: e => { if (mine(e)) location.reload(); },
  });
  // events sent between this page's rendering and the stream's opening are lost: once
  // the stream is open, compare the run's state with what the page shows
  if (runBar) source.addEventListener("open", () => checkRun(runBar));
}

async function checkRun(runBar) {
  const response = await fetch("/runs/" + encodeURIComponent(runBar.dataset.run));
  if (!response.ok) return;
  const run = await response.json();
  const shown = document.getElementById("run-status").textContent;
  const calibration = run.status === "succeeded" && "calibration" in runBar.dataset;
  const waitingForDecision = calibration && !run.decision;
  // a decision recorded while the stream was opening: the page shows the run's end
  // without it, and no event will tell
  const decisionMissed = calibration && run.decision
    && !document.getElementById("run-decision");
  if ((run.status !== shown && !waitingForDecision) || decisionMissed) location.reload();
}

function setupDecision() {
  const form = document.getElementById("decision-form");
  if (!form) return;
  form.addEventListener("submit", async ev => {
    ev.preventDefault();
    const action = ev.submitter ? ev.submitter.value : "accept";
    const comment = form.elements.comment.value;
    const r = await post("/calibrations/" + encodeURIComponent(form.dataset.run) + "/" + action,
                         { comment, operator: sessionStorage.getItem("rigctl-operator") || null });
    if (r.ok) location.reload();
  });
}

function fieldValue(el) {
  const kind = el.dataset.kind;
  if (kind === "boolean") return el.checked;
  const text = el.value.trim();
  if (text === "") return undefined;          // the procedure's default
  if (kind === "integer" || kind === "number") {
    const n = Number(text);
    return Number.isFinite(n) ? n : text;     // let the server say what is wrong
  }
  if (kind === "array") {
    return text.split(/[\s,]+/).filter(Boolean).map(v => (Number.isFinite(Number(v)) ? Number(v) : v));
  }
  if (kind === "json") {
    try { return JSON.parse(text); } catch (e) { return text; }
  }
  return text;
}

function setupStart() {
  const form = document.getElementById("start-form");
  if (!form) return;
  const operator = document.getElementById("operator");
  operator.value = sessionStorage.getItem("rigctl-operator") || "";
  let watching = null;
  const early = [];  // events that arrived before POST /runs answered with the run id
  const bar = document.getElementById("started-progress");
  const text = document.getElementById("started-text");
  const show = e => {
    if (e.type === "started") text.textContent = "running";
    if (e.type === "step") {
      bar.max = e.total || 1; bar.value = e.index || 0;
      text.textContent = "step " + e.index + "/" + e.total + ": " + e.step;
    }
    if (e.type === "finished") {
      if (e.status === "succeeded") bar.value = bar.max;
      text.textContent = "finished: " + e.status + (e.reason ? " (" + e.reason + ")" : "");
      text.className = e.status;
    }
  };
  const handle = e => {
    if (watching === null) early.push(e);
    else if (e.run_id === watching) show(e);
  };
  subscribe({ started: handle, step: handle, finished: handle });
  form.addEventListener("submit", async ev => {
    ev.preventDefault();
    showMessage("");
    const params = {};
    for (const el of form.querySelectorAll("[data-kind]")) {
      const value = fieldValue(el);
      if (value !== undefined) params[el.name] = value;
    }
    if (operator.value.trim()) sessionStorage.setItem("rigctl-operator", operator.value.trim());
    const r = await post("/runs", { procedure: form.dataset.procedure, params,
                                    operator: operator.value.trim() || null });
    if (!r.ok) return;
    watching = r.data.run_id;
    const link = document.getElementById("started-link");
    link.textContent = watching;
    link.href = "/console/runs/" + encodeURIComponent(watching);
    bar.value = 0; text.textContent = "queued (position " + r.data.position + ")"; text.className = "";
    document.getElementById("started").hidden = false;
    early.splice(0).filter(e => e.run_id === watching).forEach(show);
    showMessage("queued " + watching, "info");
  });
}

document.addEventListener("DOMContentLoaded", () => {
  setupToken(); markNav(); setupLive(); setupDecision(); setupStart();
  setupCurate(); setupTeach(); setupPreview();
});
