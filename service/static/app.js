// The viewer: upload form, job list with live progress, and the results of a finished job.
// It is a client of the API like any other (same endpoints, same API key).

const base = new URL(".", document.baseURI);
const KEY = "pwlreg-api-key";
const ACTIVE = new Set(["accepted", "running"]);
const $ = (id) => document.getElementById(id);

let selected = null;       // id of the job shown
let shownState = null;     // status + updated of the job shown, to redraw only on change
let blobs = [];            // object URLs of the job shown
let view3d = null;         // the 3D view of the job shown
let blinkTimer = null;
let knownKeys = false;     // whether the service asked for a key

// --- API calls -------------------------------------------------------------------------------

class ApiError extends Error {
  constructor(status, problem) {
    const detail = problem?.detail || problem?.title || `HTTP ${status}`;
    const more = (problem?.errors || []).map((e) => `${e.field ?? ""}: ${e.detail ?? e.message ?? ""}`);
    super(more.length > 1 ? `${detail}\n${more.join("\n")}` : detail);
    this.status = status;
  }
}

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const key = localStorage.getItem(KEY);
  if (key) headers.set("Authorization", `Bearer ${key}`);
  const response = await fetch(new URL(path, base), { ...options, headers });
  if (response.status === 401) {
    askForKey(Boolean(key));
  }
  if (!response.ok) {
    let problem = null;
    try { problem = await response.json(); } catch { /* not a problem document */ }
    throw new ApiError(response.status, problem);
  }
  return response;
}

async function blobUrl(href) {
  const url = URL.createObjectURL(await (await api(href)).blob());
  blobs.push(url);
  return url;
}

// --- API key ---------------------------------------------------------------------------------

function askForKey(rejected) {
  knownKeys = true;
  $("key-panel").hidden = false;
  $("key-button").hidden = false;
  const label = document.querySelector("#key-form label");
  label.textContent = rejected ? "This API key was refused: give another one."
                               : "This service needs an API key.";
  $("key-input").focus();
}

$("key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  localStorage.setItem(KEY, $("key-input").value.trim());
  $("key-input").value = "";
  $("key-panel").hidden = true;
  start();
});
$("key-button").addEventListener("click", () => {
  $("key-panel").hidden = !$("key-panel").hidden;
});

// --- options form, generated from /v1/options -------------------------------------------------

let optionInfos = [];

function optionField(info) {
  const label = document.createElement("label");
  label.title = info.help;
  const name = document.createElement("span");
  name.className = "name";
  name.textContent = info.name;
  label.append(name);
  let input;
  if (info.choices) {
    input = document.createElement("select");
    for (const choice of info.choices) {
      const option = document.createElement("option");
      option.value = JSON.stringify(choice);
      option.textContent = String(choice);
      option.selected = choice === info.default;
      input.append(option);
    }
  } else if (info.type === "boolean") {
    input = document.createElement("input");
    input.type = "checkbox";
    input.checked = Boolean(info.default);
  } else {
    input = document.createElement("input");
    input.type = info.type === "integer" || info.type === "number" ? "number" : "text";
    if (input.type === "number") {
      input.step = info.type === "integer" ? "1" : "any";
      const low = info.minimum ?? info.exclusive_minimum;
      const high = info.maximum ?? info.exclusive_maximum;
      if (low !== null && low !== undefined) input.min = low;
      if (high !== null && high !== undefined) input.max = high;
    }
    if (info.default !== null && info.default !== undefined) input.value = info.default;
    else input.placeholder = "default";
  }
  input.name = info.name;
  input.dataset.option = info.name;
  label.append(input);
  const help = document.createElement("small");
  help.textContent = info.help.length > 140 ? `${info.help.slice(0, 137)}...` : info.help;
  label.append(help);
  return label;
}

function optionValues() {
  const values = {};
  for (const info of optionInfos) {
    const input = document.querySelector(`[data-option="${info.name}"]`);
    let value;
    if (info.choices) value = JSON.parse(input.value);
    else if (info.type === "boolean") value = input.checked;
    else if (input.value === "") continue;
    else if (info.type === "integer" || info.type === "number") value = Number(input.value);
    else value = input.value;
    if (JSON.stringify(value) !== JSON.stringify(info.default)) values[info.name] = value;
  }
  return values;
}

async function loadOptions() {
  optionInfos = await (await api("v1/options")).json();
  const fields = $("options-fields");
  fields.replaceChildren(...optionInfos.map(optionField));
}

// --- submitting --------------------------------------------------------------------------------

$("submit-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = event.target;
  const error = $("submit-error");
  error.hidden = true;
  const data = new FormData();
  data.append("reference", form.reference.files[0]);
  data.append("moving", form.moving.files[0]);
  if (form.points.files.length) data.append("points", form.points.files[0]);
  const options = optionValues();
  if (Object.keys(options).length) data.append("options", JSON.stringify(options));
  $("submit-button").disabled = true;
  try {
    const job = await (await api("v1/jobs", { method: "POST", body: data })).json();
    await refreshJobs();
    select(job.id);
  } catch (err) {
    error.textContent = err.message;
    error.hidden = false;
  } finally {
    $("submit-button").disabled = false;
  }
});

// --- the job list ------------------------------------------------------------------------------

let pollTimer = null;

function when(iso) {
  return iso ? new Date(iso).toLocaleString() : "";
}

function jobRow(job) {
  const row = document.createElement("tr");
  row.dataset.job = job.id;
  row.className = job.id === selected ? "selected" : "";
  const progress = ACTIVE.has(job.status)
    ? `<progress max="100" value="${job.progress ?? 0}"></progress> ${job.progress ?? 0}%`
      + `${job.stage ? ` <small>${job.stage}</small>` : ""}`
    : "";
  row.innerHTML = `<td><code>${job.id.slice(0, 8)}</code></td>`
    + `<td><span class="status ${job.status}">${job.status}</span></td>`
    + `<td>${progress}</td><td>${when(job.created)}</td><td class="summary"></td>`;
  row.querySelector(".summary").textContent = job.message || "";
  row.addEventListener("click", () => select(job.id));
  return row;
}

async function refreshJobs() {
  clearTimeout(pollTimer);
  let active = false;
  try {
    const page = await (await api("v1/jobs?limit=20")).json();
    $("jobs").querySelector("tbody").replaceChildren(...page.jobs.map(jobRow));
    $("jobs-empty").hidden = page.jobs.length > 0;
    active = page.jobs.some((job) => ACTIVE.has(job.status));
    const current = page.jobs.find((job) => job.id === selected);
    if (current) await showJob(current);
  } catch (err) {
    if (err.status !== 401) console.warn("job list:", err.message);
  }
  // Faster while something runs; the list stays live either way.
  pollTimer = setTimeout(refreshJobs, active ? 1000 : 5000);
}

// --- one job -----------------------------------------------------------------------------------

async function select(id) {
  selected = id;
  shownState = null;
  for (const row of document.querySelectorAll("#jobs tbody tr")) {
    row.classList.toggle("selected", row.dataset.job === id);
  }
  const job = await (await api(`v1/jobs/${id}`)).json();
  await showJob(job);
  $("job").scrollIntoView({ behavior: "smooth", block: "start" });
}

function reset() {
  for (const url of blobs) URL.revokeObjectURL(url);
  blobs = [];
  if (view3d) view3d.dispose();
  view3d = null;
  stopBlink();
}

async function showJob(job) {
  const state = `${job.id} ${job.status} ${job.updated} ${job.progress}`;
  if (state === shownState) return;
  const finished = shownState?.split(" ")[1] === job.status && !ACTIVE.has(job.status);
  shownState = state;
  $("job").hidden = false;
  $("job-id").textContent = job.id;
  const status = $("job-status");
  status.className = `status ${job.status}`;
  status.textContent = ACTIVE.has(job.status)
    ? `${job.status} ${job.progress ?? 0}%${job.stage ? ` (${job.stage})` : ""}` : job.status;
  $("job-message").textContent = job.message || "";
  const quality = $("job-quality");
  quality.replaceChildren();
  if (job.quality?.verdict) {
    const box = document.createElement("div");
    box.className = `quality ${job.quality.verdict}`;
    box.textContent = `Quality: ${job.quality.verdict}`
      + (job.quality.reasons?.length ? ` (${job.quality.reasons.join("; ")})` : "");
    quality.append(box);
  }
  const error = $("job-error");
  error.hidden = !job.error;
  error.textContent = job.error ? `${job.error.title}: ${job.error.detail}` : "";
  if (job.status !== "successful") {
    reset();
    $("job-results").hidden = true;
    return;
  }
  if (finished) return;
  reset();
  await showResults(job);
}

function resultLinks(job) {
  const links = {};
  for (const link of job.links) {
    if (link.rel === "self") continue;
    const route = new URL(link.href, base).pathname.split("/").pop();
    links[route] = link;
  }
  return links;
}

async function setImage(id, link) {
  const img = $(id);
  img.removeAttribute("src");
  img.hidden = !link;
  if (link) img.src = await blobUrl(link.href);
}

async function showResults(job) {
  const links = resultLinks(job);
  const byName = (route) => links[route];
  $("job-results").hidden = false;

  const downloads = $("downloads");
  downloads.replaceChildren(...Object.values(links).map((link) => {
    const item = document.createElement("li");
    const a = document.createElement("a");
    a.textContent = new URL(link.href, base).pathname.split("/").pop();
    a.href = "#";
    a.title = link.title || "";
    a.addEventListener("click", async (event) => {
      event.preventDefault();
      const save = document.createElement("a");
      save.href = await blobUrl(link.href);
      save.download = a.textContent;
      save.click();
    });
    item.append(a, ` (${link.type})`);
    return item;
  }));

  const tabs = document.querySelector('.tabs[data-target="mesh-image"]');
  for (const button of tabs.querySelectorAll("button")) {
    button.onclick = async () => {
      tabs.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b === button));
      await setImage("mesh-image", byName(`${button.dataset.result}.png`));
    };
  }
  const activeTab = tabs.querySelector("button.active");
  await Promise.all([
    setImage("mesh-image", byName(`${activeTab.dataset.result}.png`)),
    setImage("checkerboard", byName("checkerboard.png")),
    setImage("difference", byName("difference.png")),
    setImage("consistency", byName("consistency.png")),
    setImage("convergence", byName("convergence.svg") || byName("convergence.png")),
    setImage("compare-base", byName("preview_reference.png")),
    setImage("compare-top", byName(`${$("compare-mesh").value}.png`)),
  ]);
  $("compare-mesh").onchange = () => setImage("compare-top", byName(`${$("compare-mesh").value}.png`));
  slide();

  const glb = byName("reconstruction.glb");
  const container = $("view3d");
  if (!glb) {
    container.innerHTML = '<p class="note">No 3D reconstruction for this job.</p>';
    return;
  }
  const buffer = await (await api(glb.href)).arrayBuffer();
  try {
    const { View3D } = await import("./view3d.js");
    view3d = new View3D(container);
    await view3d.load(buffer);
  } catch (err) {
    container.innerHTML = "";
    const note = document.createElement("p");
    note.className = "note";
    note.textContent = `The 3D view could not be shown here (${err.message}).`;
    container.append(note);
  }
  for (const button of document.querySelectorAll("#scene-tabs button")) {
    button.onclick = () => {
      document.querySelectorAll("#scene-tabs button")
        .forEach((b) => b.classList.toggle("active", b === button));
      view3d?.showScene(Number(button.dataset.scene));
    };
  }
}

// --- before/after slider and blink -------------------------------------------------------------

function slide() {
  const at = Number($("compare-slider").value);
  // Left of the line: the reference; right of it: the registered image.
  $("compare-top").style.clipPath = `inset(0 0 0 ${at}%)`;
  $("compare-top").style.opacity = "";
  $("compare-line").style.left = `calc(${at}% - 1px)`;
}

function stopBlink() {
  clearInterval(blinkTimer);
  blinkTimer = null;
  $("blink").textContent = "Blink";
  slide();
}

$("compare-slider").addEventListener("input", () => { stopBlink(); slide(); });
$("blink").addEventListener("click", () => {
  if (blinkTimer) { stopBlink(); return; }
  $("blink").textContent = "Stop";
  $("compare-top").style.clipPath = "none";
  $("compare-line").style.left = "-10px";
  let on = true;
  blinkTimer = setInterval(() => {
    on = !on;
    $("compare-top").style.opacity = on ? "1" : "0";
  }, 600);
});

// --- start -------------------------------------------------------------------------------------

async function start() {
  try {
    await loadOptions();
  } catch (err) {
    if (err.status === 401) return;  // the key panel is open; start again with the key
    $("submit-error").textContent = `Options unavailable: ${err.message}`;
    $("submit-error").hidden = false;
  }
  if (knownKeys) $("key-button").hidden = false;
  await refreshJobs();
}

start();
