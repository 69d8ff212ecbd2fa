// midview dashboard: a single page on the REST API (no build step). Hash routes:
//   #/projects  #/projects/{id}  #/jobs/{id}  #/jobs/{id}/map  #/jobs/{id}/ground/{file}
// The API key lives in sessionStorage and goes in the Authorization header of every request; the job's
// event stream is read with fetch (EventSource cannot send headers).
// A static report (`midview demo`'s report.html, cli/report_page.py) carries the API's answers for one job in
// #midview-snapshot: the same pages then read those, read only, from the file system.

const main = document.getElementById("main");
const nav = document.getElementById("nav");
const SNAP = (() => { const el = document.getElementById("midview-snapshot"); return el ? JSON.parse(el.textContent) : null; })();
let key = SNAP ? "static report" : sessionStorage.getItem("midview-key");
let leaving = [];  // cleanups of the current page (event streams)

// -- helpers -------------------------------------------------------------------------------------
function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (v !== null && v !== undefined && v !== false) el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) el.append(c.nodeType ? c : String(c));
  return el;
}
function toast(msg) {
  const t = document.getElementById("toast");
  t.textContent = msg; t.hidden = false;
  clearTimeout(toast.timer); toast.timer = setTimeout(() => { t.hidden = true; }, 6000);
}
function detail(body) {
  const d = body && body.detail !== undefined ? body.detail : body;
  if (typeof d === "string") return d;
  if (d && d.message) return d.message + (d.errors ? ": " + d.errors.slice(0, 5).join("; ") : "");
  if (Array.isArray(d)) return d.map((e) => (fieldOf(e) ? `${fieldOf(e)}: ` : "") + (e.msg || JSON.stringify(e))).join("; ");
  return JSON.stringify(d);
}
// the field a 422 error is about: the last name of its location past "body" and "options"
function fieldOf(e) { return (e.loc || []).filter((x) => !["body", "options", "query", "path"].includes(x)).join("."); }
class ApiError extends Error { constructor(status, body) { super(detail(body)); this.status = status; this.body = body; } }
async function snapshotAnswer(method, path, raw) {  // a static report's recorded answer
  const p = path.split("?")[0];
  if (method !== "GET") throw new ApiError(405, "a static report is read only: run midview serve to change anything");
  if (p in SNAP.json) return raw ? new Response(JSON.stringify(SNAP.json[p])) : structuredClone(SNAP.json[p]);
  if (p in SNAP.blobs && raw) return fetch(SNAP.blobs[p]);
  throw new ApiError(404, `not in this report: ${p}`);
}
async function api(method, path, body, raw = false) {
  if (SNAP) return snapshotAnswer(method, path, raw);
  const opts = { method, headers: { Authorization: `Bearer ${key}` } };
  if (body instanceof FormData) opts.body = body;
  else if (body !== undefined) { opts.body = JSON.stringify(body); opts.headers["Content-Type"] = "application/json"; }
  const r = await fetch(path, opts);
  if (raw) { if (!r.ok) throw new ApiError(r.status, await r.text()); return r; }
  const text = await r.text();
  const data = text ? JSON.parse(text) : null;
  if (!r.ok) throw new ApiError(r.status, data);
  return data;
}
const fmtBytes = (n) => n > 1e6 ? `${(n / 1e6).toFixed(1)} MB` : `${Math.max(1, Math.round(n / 1e3))} kB`;
const fmtS = (x) => x === null || x === undefined ? "" : x < 60 ? `${x.toFixed(1)} s` : `${(x / 60).toFixed(1)} min`;
function outcomeText(o) {
  if (!o || !o.images) return "";
  const g = o.images.ground !== undefined ? `ground ${o.registered.ground || 0}/${o.images.ground}` : "";
  const a = o.images.aerial !== undefined ? `aerial ${o.registered.aerial || 0}/${o.images.aerial}` : "";
  return [g, a].filter(Boolean).join(", ");
}
const CAUSE_WORDS = {  // services.sfm.combined.report.CAUSES, in a few words
  "no-aerial-view": "views show nothing the aerial images see", "views-without-ties": "views gave no aerial tie",
  "ties-without-pose": "ties too few for a pose", "chained-to-unregistered": "tied only to unregistered images",
  "ambiguous": "pose dropped as ambiguous",
};
function headline(o) {  // "N of M ground images registered", and why the others were left out
  if (!o || !o.images || o.images.ground === undefined) return "";
  const causes = Object.entries(o.causes || {}).map(([c, n]) => `${n} ${CAUSE_WORDS[c] || c}`);
  return [h("span", { id: "job-registered" }, `${o.registered.ground || 0} of ${o.images.ground} ground images registered`),
    causes.length ? h("span", { class: "muted", id: "job-causes" }, ` — left out: ${causes.join(", ")}`) : ""];
}
const warned = (job) => job.status === "succeeded" && job.outcome && job.outcome.result === "warnings";
async function authedUrl(path) {  // a blob: URL of an API download (it needs the key)
  if (SNAP) { if (path in SNAP.blobs) return SNAP.blobs[path]; throw new ApiError(404, `not in this report: ${path}`); }
  const r = await api("GET", path, undefined, true);
  return URL.createObjectURL(await r.blob());
}
function isApiUrl(url) { return SNAP ? url in SNAP.blobs || url in SNAP.json : new URL(url, location.href).origin === location.origin; }
async function downloadArtifact(a) {
  if (SNAP && !isApiUrl(a.download_url)) { window.open(a.download_url, "_blank"); return; }  // a file beside the report
  const url = isApiUrl(a.download_url) ? await authedUrl(a.download_url) : a.download_url;
  const link = h("a", { href: url, download: a.name.split("/").pop() });
  document.body.append(link); link.click(); link.remove();
}

// -- sign in -------------------------------------------------------------------------------------
function signIn() {
  nav.replaceChildren();
  const input = h("input", { type: "password", id: "api-key", placeholder: "mv_…", autocomplete: "off" });
  const err = h("p", { class: "bad", id: "signin-error" });
  const form = h("form", { id: "signin", onsubmit: async (e) => {
    e.preventDefault();
    key = input.value.trim();
    try {
      await api("GET", "/projects"); sessionStorage.setItem("midview-key", key);
      // a shared link (a project, a job, a ground image) opens where it points once signed in
      if (!/^#\/(projects|jobs)\/./.test(location.hash)) history.replaceState(null, "", "#/projects");
      route();
    }
    catch (x) { err.textContent = `sign in failed: ${x.message}`; key = null; }
  } }, h("label", { for: "api-key" }, "API key"), input, h("p"), h("button", { type: "submit" }, "Sign in"), err);
  main.replaceChildren(h("section", {}, h("h1", {}, "Sign in"), form,
    h("p", { class: "muted" }, "midview serve prints a key at its first start; operators make more with midview admin.")));
}

// -- projects ------------------------------------------------------------------------------------
async function projectsPage() {
  const projects = await api("GET", "/projects");
  const rows = await Promise.all(projects.map(async (p) => {
    const jobs = await api("GET", `/projects/${p.id}/jobs`);
    const last = jobs[jobs.length - 1];
    return h("tr", { class: "project-row" },
      h("td", {}, h("a", { href: `#/projects/${p.id}` }, p.name)),
      h("td", { class: "num" }, jobs.length),
      h("td", {}, last ? h("a", { href: `#/jobs/${last.id}`, class: `status ${last.status}` }, last.status) : "-"),
      h("td", { class: "hide-phone" }, last ? outcomeText(last.outcome) : ""),
      h("td", { class: "muted hide-phone" }, new Date(p.created_at).toLocaleString()));
  }));
  const name = h("input", { type: "text", id: "project-name", placeholder: "project name", required: true });
  const crs = h("input", { type: "text", id: "project-crs", placeholder: "output CRS (optional), e.g. EPSG:32633" });
  const form = h("form", { id: "create-project", onsubmit: async (e) => {
    e.preventDefault();
    try {
      const p = await api("POST", "/projects", { name: name.value.trim(), ...(crs.value.trim() ? { crs: crs.value.trim() } : {}) });
      location.hash = `#/projects/${p.id}`;
    } catch (x) { toast(x.message); }
  } }, h("div", { class: "grid2" }, name, crs), h("p"), h("button", { type: "submit" }, "Create project"));
  main.replaceChildren(
    h("h1", {}, "Projects"),
    h("section", {}, h("table", { id: "projects" },
      h("thead", {}, h("tr", {}, h("th", {}, "name"), h("th", { class: "num" }, "jobs"), h("th", {}, "last job"),
        h("th", { class: "hide-phone" }, "outcome"), h("th", { class: "hide-phone" }, "created"))),
      h("tbody", {}, rows.length ? rows : h("tr", {}, h("td", { colspan: 5, class: "muted" }, "no projects yet"))))),
    h("section", {}, h("h2", {}, "New project"), form));
}

// -- uploads (the API's resumable multipart uploads) -------------------------------------------------
function putPart(url, blob, auth, onProgress) {  // XHR: fetch has no upload progress
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("PUT", url);
    if (auth) xhr.setRequestHeader("Authorization", `Bearer ${key}`);
    xhr.upload.onprogress = (e) => onProgress(e.loaded);
    xhr.onload = () => {
      if (xhr.status !== 200) return reject(new Error(`part upload: HTTP ${xhr.status} ${xhr.responseText.slice(0, 200)}`));
      resolve(xhr.getResponseHeader("ETag") || JSON.parse(xhr.responseText).etag);
    };
    xhr.onerror = () => reject(new Error("part upload: network error"));
    xhr.send(blob);
  });
}
async function uploadFile(pid, set, file, onProgress) {
  const name = `${set}/${file.name}`;
  let up;
  try { up = await api("POST", `/projects/${pid}/uploads`, { name, size: file.size }); }
  catch (x) {
    if (x.status !== 409) throw x;
    if (x.body && x.body.detail && x.body.detail.sha256) { onProgress(file.size); return "present"; }
    up = (await api("GET", `/projects/${pid}/uploads`)).find((u) => u.name === name);  // resume it
    if (!up || up.size !== file.size) throw x;
  }
  const parts = await api("GET", `/projects/${pid}/uploads/${up.id}/parts`);
  const todo = [...new Set([...parts.missing, ...parts.wrong_size])];
  let done = file.size - todo.reduce((n, k) => n + Math.min(up.part_size, file.size - (k - 1) * up.part_size), 0);
  onProgress(done);
  for (const n of todo) {
    const where = await api("GET", `/projects/${pid}/uploads/${up.id}/parts/${n}`);
    const blob = file.slice((n - 1) * up.part_size, n * up.part_size);
    await putPart(where.url, blob, where.needs_auth || isApiUrl(where.url), (b) => onProgress(done + b));
    done += blob.size;
  }
  await api("POST", `/projects/${pid}/uploads/${up.id}/complete`, {});
  onProgress(file.size);
  return todo.length < up.part_count ? "resumed" : "uploaded";
}
const IMAGE = /\.(jpe?g|png|tiff?)$/i;
async function filesOf(dataTransfer) {  // files of a drop, folders walked
  const out = [];
  async function walk(entry) {
    if (entry.isFile) out.push(await new Promise((res, rej) => entry.file(res, rej)));
    else if (entry.isDirectory) {
      const reader = entry.createReader();
      for (;;) {
        const batch = await new Promise((res, rej) => reader.readEntries(res, rej));
        if (!batch.length) break;
        for (const e of batch) await walk(e);
      }
    }
  }
  const entries = [...dataTransfer.items].map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
  if (entries.length) for (const e of entries) await walk(e); else out.push(...dataTransfer.files);
  return out.filter((f) => IMAGE.test(f.name));
}
function uploader(pid, set, onDone) {
  const list = h("tbody");
  const total = h("progress", { max: 1, value: 0, id: `${set}-total` });
  const totalText = h("span", { class: "muted", id: `${set}-total-text` }, "");
  const input = h("input", { type: "file", multiple: true, accept: "image/*", id: `${set}-files`,
    onchange: () => run([...input.files]) });
  const folder = h("input", { type: "file", webkitdirectory: true, id: `${set}-folder`,
    onchange: () => run([...folder.files].filter((f) => IMAGE.test(f.name))) });
  const zone = h("div", { class: "drop", id: `${set}-drop`,
    ondragover: (e) => { e.preventDefault(); zone.classList.add("over"); },
    ondragleave: () => zone.classList.remove("over"),
    ondrop: async (e) => { e.preventDefault(); zone.classList.remove("over"); run(await filesOf(e.dataTransfer)); } },
  `drop ${set} images or folders here`, h("br"), input, h("span", { class: "muted" }, " or a folder: "), folder);
  async function run(files) {
    const size = files.reduce((n, f) => n + f.size, 0);
    const sent = new Map();
    let ok = 0, failed = 0;
    const update = () => {
      const n = [...sent.values()].reduce((a, b) => a + b, 0);
      total.value = size ? n / size : 1;
      totalText.textContent = `${ok + failed}/${files.length} files, ${fmtBytes(n)} of ${fmtBytes(size)}` + (failed ? `, ${failed} failed` : "");
    };
    const queue = files.map((f) => {
      const bar = h("progress", { max: f.size || 1, value: 0 });
      const state = h("td", { class: "muted" }, "waiting");
      list.append(h("tr", { class: "upload-row" }, h("td", {}, f.name), h("td", { class: "num hide-phone" }, fmtBytes(f.size)), h("td", {}, bar), state));
      return { f, bar, state };
    });
    const worker = async () => {
      for (let item = queue.shift(); item; item = queue.shift()) {
        try {
          const how = await uploadFile(pid, set, item.f, (b) => { item.bar.value = b; sent.set(item.f, b); update(); });
          item.state.textContent = how; item.state.className = "ok"; ok++;
        } catch (x) { item.state.textContent = x.message; item.state.className = "bad"; failed++; }
        update();
      }
    };
    await Promise.all([worker(), worker(), worker()]);
    onDone();
  }
  return h("div", {}, h("h2", {}, `${set} images`), zone, h("p"), total, totalText,
    h("table", { id: `${set}-uploads` }, list));
}

// -- the job options form (GET /options: profiles, each option's default per profile, its help) ----------
async function optionsForm(counts) {
  // with the project's image counts: each profile's estimated time (the cost model of GET /options)
  const spec = await api("GET", counts ? `/options?aerial=${counts.aerial}&ground=${counts.ground}` : "/options");
  const offered = (spec.profiles.find((p) => p.offered) || spec.profiles[0]).name;
  const profile = h("select", { id: "opt-profile" }, spec.profiles.map((p) =>
    h("option", { value: p.name, selected: p.name === offered }, `${p.name}${p.offered ? " (this service's workers)" : ""}`)));
  const profileHelp = h("p", { class: "muted", id: "opt-profile-help" });
  const estimate = h("p", { id: "opt-estimate" });
  const fields = {}, rows = [];
  const stagesSpec = spec.options.find((o) => o.name === "stages");
  const stageBoxes = stagesSpec.choices.map((st) => h("label", { class: "stage-choice" },
    h("input", { type: "checkbox", id: `opt-stage-${st}`, value: st, checked: stagesSpec.default.includes(st) }), ` ${st} `));
  for (const o of spec.options) {
    if (o.name === "stages" || o.name === "profile") continue;
    const id = `opt-${o.name.replaceAll("_", "-")}`;
    const input = o.choices
      ? h("select", { id }, h("option", { value: "" }, "(profile's)"), o.choices.map((c) => h("option", { value: c }, c)))
      : h("input", { id, type: o.type.startsWith("integer") || o.type.startsWith("number") ? "number" : "text",
        min: o.minimum, max: o.maximum, step: o.type.startsWith("integer") ? 1 : "any" });
    fields[o.name] = { input, spec: o };
    rows.push(h("tr", { class: "option-row" }, h("th", {}, h("label", { for: id }, o.name)), h("td", {}, input),
      h("td", { class: "muted hide-phone" }, o.help)));
  }
  const showDefaults = () => {
    const p = spec.profiles.find((x) => x.name === profile.value);
    profileHelp.textContent = p ? p.help : "";
    const e = p && p.estimate;
    estimate.textContent = !e ? "" : e.total_s === null ? "no time estimate: this profile was not timed"
      : `about ${Math.max(1, Math.round(e.total_s / 60))} min for ${e.aerial} aerial and ${e.ground} ground images on 2 CPU cores`
        + (e.relative_error.median !== null ? ` (the estimate is off by ${Math.round(100 * e.relative_error.median)}% typically)` : "");
    for (const { input, spec: o } of Object.values(fields)) {
      const d = o.defaults[profile.value];
      if (input.tagName === "SELECT") input.options[0].textContent = `${d} (profile's)`;
      else input.placeholder = d === null ? "none" : String(d);
    }
  };
  profile.addEventListener("change", showDefaults);
  showDefaults();
  const advanced = h("textarea", { id: "job-options", spellcheck: "false" }, "{}");
  const read = () => {  // the options given: the profile, the stages ticked, the fields filled, then the JSON
    const out = { profile: profile.value, stages: stageBoxes.map((l) => l.firstChild).filter((c) => c.checked).map((c) => c.value) };
    for (const [name, { input, spec: o }] of Object.entries(fields)) {
      input.classList.remove("bad-field");
      if (input.value === "") continue;
      out[name] = o.type.startsWith("integer") ? parseInt(input.value, 10) : o.type.startsWith("number") ? Number(input.value) : input.value;
    }
    return { ...out, ...JSON.parse(advanced.value || "{}") };
  };
  const mark = (x) => {  // outline the fields a 422 names
    for (const e of (x.body && Array.isArray(x.body.detail) ? x.body.detail : [])) {
      const f = fields[fieldOf(e).split(".")[0]];
      if (f) f.input.classList.add("bad-field");
    }
  };
  const form = h("div", { id: "job-form" }, h("p", {}, h("label", { for: "opt-profile" }, "profile "), profile), profileHelp, estimate,
    h("p", { id: "opt-stages" }, "stages: ", stageBoxes),
    h("details", {}, h("summary", {}, "options"), h("table", { id: "options" }, h("tbody", {}, rows))),
    h("details", {}, h("summary", {}, "more options as JSON"), advanced));
  const update = async (c) => {  // the project's image counts changed: estimate again
    try { spec.profiles = (await api("GET", `/options?aerial=${c.aerial}&ground=${c.ground}`)).profiles; showDefaults(); }
    catch { /* the estimate stays as it was */ }
  };
  return { form, read, mark, update };
}

// -- a project ---------------------------------------------------------------------------------------
async function projectPage(pid) {
  const p = await api("GET", `/projects/${pid}`);
  const jobs = await api("GET", `/projects/${pid}/jobs`);
  nav.replaceChildren(h("a", { href: "#/projects" }, "projects"), h("span", {}, p.name));
  const counts = h("p", { id: "image-counts" }, `${p.images.aerial} aerial, ${p.images.ground} ground images, ${p.pos_records} POS rows`);
  const refresh = async () => {
    const q = await api("GET", `/projects/${pid}`);
    counts.textContent = `${q.images.aerial} aerial, ${q.images.ground} ground images, ${q.pos_records} POS rows`;
    if (jobForm) await jobForm.update(q.images);
  };
  const posResult = h("div", { id: "pos-result" });
  const posInput = h("input", { type: "file", id: "pos-file", onchange: async () => {
    const form = new FormData(); form.append("file", posInput.files[0]);
    posResult.replaceChildren();
    try {
      const r = await api("POST", `/projects/${pid}/pos`, form);
      posResult.append(h("p", { class: "ok" }, `${r.stored} rows stored (${r.format}), ${r.total} in all`),
        r.warnings.length ? h("ul", { class: "errors warn" }, r.warnings.slice(0, 50).map((w) => h("li", {}, w))) : "");
      refresh();
    } catch (x) {
      const errs = (x.body && x.body.detail && x.body.detail.errors) || [];
      posResult.append(h("p", { class: "bad" }, x.message.split(":")[0]), h("ul", { class: "errors" }, errs.slice(0, 100).map((e) => h("li", {}, e))));
    }
  } });
  const camInput = h("input", { type: "file", id: "cameras-file", accept: ".json", onchange: async () => {
    try { await api("PUT", `/projects/${pid}/cameras`, JSON.parse(await camInput.files[0].text())); toast("cameras.json stored"); }
    catch (x) { toast(`cameras.json: ${x.message}`); }
  } });
  const jobForm = SNAP ? null : await optionsForm(p.images);
  const start = h("button", { id: "start-job", onclick: async () => {
    try {
      const job = await api("POST", `/projects/${pid}/jobs`, { options: jobForm.read() });
      location.hash = `#/jobs/${job.id}`;
    } catch (x) { jobForm.mark(x); toast(`job: ${x.message}`); }
  } }, "Start job");
  main.replaceChildren(
    h("h1", {}, p.name), counts,
    ...(SNAP ? [] : [h("section", { class: "grid2" }, uploader(pid, "aerial", refresh), uploader(pid, "ground", refresh)),
    h("section", { class: "grid2" },
      h("div", {}, h("h2", {}, "POS"), h("p", { class: "muted" }, "CSV, ODM geo.txt or JSON; every row is checked before it is stored"), posInput, posResult),
      h("div", {}, h("h2", {}, "Intrinsics"), h("p", { class: "muted" }, "cameras.json (optional with EXIF focal lengths)"), camInput)),
    h("section", {}, h("h2", {}, "New job"), jobForm.form, h("p"), start)]),
    h("section", {}, h("h2", {}, "Jobs"), h("table", { id: "jobs" }, h("tbody", {}, jobs.map((j) => h("tr", {},
      h("td", {}, h("a", { href: `#/jobs/${j.id}` }, j.id.slice(0, 8))), h("td", { class: `status ${j.status}` }, j.status),
      h("td", {}, outcomeText(j.outcome)), h("td", { class: "muted hide-phone" }, new Date(j.created_at).toLocaleString())))))));
}

// -- a job ---------------------------------------------------------------------------------------------
async function follow(jobId, onEvent) {  // the job's server-sent events, read with fetch; reconnects
  if (SNAP) return;  // a static report's job is finished
  const ctrl = new AbortController();
  leaving.push(() => ctrl.abort());
  for (let wait = 500; !ctrl.signal.aborted; wait = Math.min(2 * wait, 10000)) {
    try {
      const r = await fetch(`/jobs/${jobId}/events`, { headers: { Authorization: `Bearer ${key}` }, signal: ctrl.signal });
      if (!r.ok) throw new Error(`event stream: HTTP ${r.status}`);
      const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += value;
        let i;
        while ((i = buf.indexOf("\n\n")) >= 0) {
          const block = buf.slice(0, i); buf = buf.slice(i + 2);
          const ev = /^event: (.*)$/m.exec(block), data = /^data: (.*)$/m.exec(block);
          if (!ev || !data) continue;
          wait = 500;
          await onEvent(ev[1], JSON.parse(data[1]));
          if (ev[1] === "end" || ev[1] === "error") return;
        }
      }
    } catch (x) { if (x.name === "AbortError") return; console.warn(x.message); }
    await new Promise((res) => setTimeout(res, wait));  // dropped before its end: the next stream starts with the job's state
  }
}
function jobNav(job, project) {
  nav.replaceChildren(h("a", { href: "#/projects" }, "projects"), h("a", { href: `#/projects/${job.project_id}` }, project.name),
    h("a", { href: `#/jobs/${job.id}` }, `job ${job.id.slice(0, 8)}`), h("a", { href: `#/jobs/${job.id}/map`, id: "map-link" }, "map"),
    h("a", { href: `#/jobs/${job.id}/3d`, id: "view3d-link" }, "3D"),
    // a synthetic survey's report: the methods against its ground truth, a tab of its own
    SNAP && SNAP.evaluation ? h("a", { href: `#/jobs/${job.id}/evaluation`, id: "evaluation-link" }, "evaluation") : "");
}
async function evaluationPage(jobId) {  // a static report's evaluation against the survey's ground truth
  const job = await api("GET", `/jobs/${jobId}`);
  const project = await api("GET", `/projects/${job.project_id}`);
  jobNav(job, project);
  main.replaceChildren(h("h1", {}, `Job ${jobId.slice(0, 8)}: evaluation`),
    SNAP && SNAP.evaluation ? evaluationSection(SNAP.evaluation) : h("p", { class: "muted" }, "a job of uploaded images has no ground truth to evaluate against"));
}
function stageRows(job) {
  const wanted = job.options.stages;  // the API's JobOptions: stage names from services.pipeline's registry
  const runs = job.stages.filter((r) => r.attempt === job.attempt);
  return wanted.map((st) => {
    const run = [...runs].reverse().find((r) => r.stage === st);
    const status = run ? run.status : (job.status === "queued" || job.status === "running" ? "pending" : "-");
    // the running stage's share: the job's progress is (index of the stage + its fraction) / stages
    const i = wanted.indexOf(st), current = job.current_stage === st && run && run.status === "running";
    const share = current ? Math.min(1, Math.max(0, job.progress * wanted.length - i)) : null;
    const value = run && ["succeeded", "skipped"].includes(run.status) ? 1 : (current ? share : 0);
    const bar = h("progress", { max: 1, value, "data-stage": st });
    // a stage whose outputs were up to date was not run again: say so (a rerun that changed nothing)
    const label = current ? `${status} ${Math.round(100 * share)}%` : status === "skipped" ? "skipped: up to date" : status;
    return h("tr", { class: "stage-row", "data-stage": st }, h("td", {}, st), h("td", { class: `status ${status}` }, label),
      h("td", {}, bar), h("td", { class: "num" }, run ? fmtS(run.duration_s) : ""),
      h("td", { class: "bad" }, run && run.error ? run.error.slice(0, 300) : ""));
  });
}
function evaluationSection(ev) {  // a static report's table of the methods against the ground truth
  return h("section", { id: "evaluation" }, h("h2", {}, ev.title),
    h("div", { class: "scroll" }, h("table", { id: "evaluation-table" },
      h("thead", {}, h("tr", {}, ev.columns.map((c, i) => h("th", { class: i ? "num" : "" }, c)))),
      h("tbody", {}, ev.rows.map((r) => h("tr", { class: "evaluation-row" }, r.map((v, i) => h("td", { class: i ? "num" : "" }, v))))))),
    (ev.notes || []).map((n) => h("p", { class: "muted" }, n)),
    (ev.pictures || []).map((p) => h("figure", { class: "evaluation-picture" }, h("img", { class: "photo", src: p.src, alt: p.caption }), h("figcaption", { class: "muted" }, p.caption))));
}
// the ground images of a finished job as thumbnails, registered first, then grouped by the cause that
// left them out, each linked to its page (at most GRID_MAX pictures; the rest by name)
const GRID_MAX = 60;
async function groundGrid(jobId, project) {
  const gj = await camerasOf(jobId);
  if (!gj) return "";
  const ground = gj.features.map((f) => f.properties).filter((p) => p.set === "ground");
  const groups = new Map([["registered", []]]);
  for (const p of ground) {
    const g = p.registered ? "registered" : p.cause || "not registered";
    if (!groups.has(g)) groups.set(g, []);
    groups.get(g).push(p);
  }
  let shown = 0;
  const sections = [];
  for (const [g, ps] of groups) {
    if (!ps.length) continue;
    const cells = await Promise.all(ps.map(async (p) => {
      const file = p.name.replace(/^ground\//, "");
      const href = `#/jobs/${jobId}/ground/${file.split("/").map(encodeURIComponent).join("/")}`;
      const pic = shown++ < GRID_MAX
        ? h("img", { alt: p.name, src: await authedUrl(`/projects/${project.id}/images/${p.name}/download`).catch(() => "") }) : "";
      return h("a", { class: `thumb ${p.registered ? "ok" : "bad"}`, href, title: p.reason || p.name }, pic, h("span", {}, file));
    }));
    const label = g === "registered" ? "registered" : CAUSE_WORDS[g] || g;
    sections.push(h("div", { class: "thumb-group", "data-group": g }, h("h3", {}, `${label} (${ps.length})`), h("div", { class: "thumbs" }, cells)));
  }
  return h("section", { id: "ground-grid" }, h("h2", {}, "Ground images"), sections);
}

async function jobPage(jobId) {
  let job = await api("GET", `/jobs/${jobId}`);
  const project = await api("GET", `/projects/${job.project_id}`);
  jobNav(job, project);
  const status = h("span", { id: "job-status", class: `status ${job.status}` }, job.status);
  const result = h("span", { id: "job-result", class: "status warnings" });
  const head = h("h2", { id: "job-headline" });
  const overall = h("progress", { id: "job-progress", max: 100, value: job.progress_percent });
  const pct = h("span", { id: "job-percent" }, `${job.progress_percent.toFixed(0)}%`);
  const stages = h("tbody", { id: "stages" }, stageRows(job));
  const log = h("div", { class: "log", id: "job-log" });
  const outcome = h("p", { id: "job-outcome" });
  const arts = h("tbody", { id: "artifacts" });
  const bundles = h("p", { id: "bundles", class: "row" });
  const grid = h("div", {});
  const cancel = h("button", { class: "secondary", id: "cancel-job", onclick: async () => {
    try { await api("POST", `/jobs/${jobId}/cancel`); } catch (x) { toast(x.message); }
  } }, "Cancel");
  const from = h("select", { id: "rerun-from" }, h("option", { value: "" }, "from the start"),
    job.options.stages.map((st) => h("option", { value: st }, `from ${st}`)));
  // forced: the stages run again even where their inputs are unchanged (otherwise "skipped: up to date")
  const force = h("label", { class: "muted", title: "run the stages again even where nothing changed" }, h("input", { type: "checkbox", id: "rerun-force" }), " force");
  const rerun = h("button", { class: "secondary", id: "rerun-job", onclick: async () => {
    try { await api("POST", `/jobs/${jobId}/rerun`, { from_stage: from.value || null, force: force.firstChild.checked }); jobPage(jobId); } catch (x) { toast(x.message); }
  } }, "Rerun");
  const logLine = (t) => { log.append(`${new Date().toLocaleTimeString()}  ${t}\n`); log.scrollTop = log.scrollHeight; };
  const render = async () => {
    status.textContent = job.status; status.className = `status ${warned(job) ? "warnings" : job.status}`;
    result.textContent = warned(job) ? "finished with warnings" : "";
    head.replaceChildren(...[headline(job.outcome)].flat());
    overall.value = job.progress_percent; pct.textContent = `${job.progress_percent.toFixed(0)}%`;
    stages.replaceChildren(...stageRows(job));
    const final = ["succeeded", "failed", "cancelled"].includes(job.status);
    cancel.disabled = final; rerun.disabled = !final;
    outcome.replaceChildren(job.outcome ? `${outcomeText(job.outcome)} ${job.outcome.warnings.length ? "— " + job.outcome.warnings.join("; ") : ""}` : "",
      job.error ? h("span", { class: "bad" }, job.error) : "");
    if (final) {
      const list = await api("GET", `/jobs/${jobId}/artifacts`);
      if (!grid.firstChild) grid.replaceChildren(await groundGrid(jobId, project).catch(() => ""));
      // the named products first: one zip each (GET /jobs/{id}/bundles/{name}.zip)
      const has = (prefix) => list.some((a) => a.name.startsWith(prefix));
      bundles.replaceChildren(...(SNAP ? [] : [["gis", "GIS bundle (GeoPackage, OPK, LAS)", "combined/gis/"],
        ["colmap", "COLMAP model bundle", "combined/sparse/"]].filter(([, , p]) => has(p)).map(([b, label]) =>
        h("button", { class: "secondary", id: `bundle-${b}`, onclick: () => downloadArtifact(
          { name: `midview-${jobId.slice(0, 8)}-${b}.zip`, download_url: `/jobs/${jobId}/bundles/${b}.zip` }).catch((x) => toast(x.message)) }, label))));
      arts.replaceChildren(...list.map((a) => h("tr", { class: "artifact-row" }, h("td", {}, a.name), h("td", { class: "muted hide-phone" }, a.kind),
        h("td", { class: "num" }, a.size_bytes ? fmtBytes(a.size_bytes) : ""),
        h("td", {}, h("button", { class: "link", onclick: () => downloadArtifact(a).catch((x) => toast(x.message)) }, "download")))));
    }
  };
  main.replaceChildren(
    h("h1", {}, `Job ${jobId.slice(0, 8)} of ${project.name}`), head,
    h("section", {}, h("div", { class: "row" }, status, result, pct, SNAP ? "" : [cancel, from, force, rerun]), h("p"), overall, outcome,
      h("table", {}, h("thead", {}, h("tr", {}, h("th", {}, "stage"), h("th", {}, "status"), h("th", {}, "progress"), h("th", { class: "num" }, "time"), h("th", {}, ""))), stages)),
    grid,
    SNAP && SNAP.evaluation ? h("p", { class: "muted" }, "A synthetic survey: the methods against its ground truth are under ",
      h("a", { href: `#/jobs/${jobId}/evaluation`, id: "evaluation-tab-link" }, "evaluation"), ".") : "",
    h("section", {}, h("h2", {}, "Log"), log),
    h("section", {}, h("h2", {}, "Results"), bundles, h("table", {}, arts)));
  await render();
  // the job's log as the server keeps it (every stage run, every attempt: what each stage logged while
  // it ran, GET /jobs/{id}/log), then what its progress reports say live
  if (SNAP) {  // a static report has the stage runs only
    const history = job.stages.flatMap((r) => [[r.started_at, `started ${r.stage} (attempt ${r.attempt}${r.worker ? ", " + r.worker : ""})`],
      ...(r.finished_at ? [[r.finished_at, `${r.status} ${r.stage} (${fmtS(r.duration_s)})${r.error ? ": " + r.error.slice(0, 200) : ""}`]] : [])]);
    history.sort((a, b) => new Date(a[0]) - new Date(b[0]));
    for (const [t, text] of history) log.append(`${new Date(t).toLocaleTimeString()}  ${text}\n`);
  } else {
    try { log.append(await (await api("GET", `/jobs/${jobId}/log`, undefined, true)).text()); log.scrollTop = log.scrollHeight; } catch (x) { log.append(`the job's log could not be read: ${x.message}\n`); }
  }
  let lastStage = job.current_stage, lastMessage = job.progress_message;
  follow(jobId, async (ev, data) => {
    if (ev === "progress") {
      if (data.stage !== lastStage || data.status !== job.status) logLine(`${data.status} ${data.stage || ""}`);
      if (data.message && data.message !== lastMessage) logLine(`${data.stage || ""}: ${data.message}`);
      lastMessage = data.message;
      const refetch = data.stage !== lastStage || data.status !== job.status;
      lastStage = data.stage;
      job = { ...job, status: data.status, current_stage: data.stage, progress_percent: data.progress_percent,
        outcome: data.outcome, error: data.error };
      if (refetch) job = await api("GET", `/jobs/${jobId}`);
      await render();
    } else if (ev === "end") {
      logLine(`end: ${data.status}`);
      // the status read may lag the event by a moment (another API process's cache): ask until it agrees
      for (let i = 0; i < 10; i++) {
        job = await api("GET", `/jobs/${jobId}`);
        if (job.status === data.status) break;
        await new Promise((r) => setTimeout(r, 300));
      }
      job = { ...job, status: data.status }; await render();
    }
  });
}

// -- the map and the ground images -----------------------------------------------------------------
async function layerOf(jobId, name, list = null) {  // a JSON artifact of the job (from its list when given), or null
  const arts = list || await api("GET", `/jobs/${jobId}/artifacts`);
  const a = arts.find((x) => x.name === name);
  if (!a) return null;
  const r = isApiUrl(a.download_url) ? await api("GET", a.download_url, undefined, true) : await fetch(a.download_url);
  return r.json();
}
const camerasOf = (jobId) => layerOf(jobId, "combined/gis/cameras.geojson");  // the combined model's cameras
async function artifactUrl(jobId, name, list = null) {  // a URL an <img> can load for a job's artifact, or null
  const a = (list || await api("GET", `/jobs/${jobId}/artifacts`)).find((x) => x.name === name);
  if (!a) return null;
  return isApiUrl(a.download_url) ? authedUrl(a.download_url) : a.download_url;
}
// an arrowhead (a small triangle, `len` metres) at the end of the segment a -> b ([lat, lon] each)
function arrowHead(a, b, len) {
  const k = Math.cos((b[0] * Math.PI) / 180), dy = (b[0] - a[0]) * 110540, dx = (b[1] - a[1]) * 111320 * k;
  const n = Math.hypot(dx, dy) || 1, ux = dx / n, uy = dy / n;
  const at = (x, y) => [b[0] + y / 110540, b[1] + x / (111320 * k)];
  return [at(0, 0), at(-len * ux - 0.5 * len * uy, -len * uy + 0.5 * len * ux), at(-len * ux + 0.5 * len * uy, -len * uy - 0.5 * len * ux)];
}
// the POS-to-registered offset's colour by its length: within 1 m, 1-3 m, farther
const offsetColour = (m) => m <= 1 ? "#2e7d32" : m <= 3 ? "#e8890c" : "#c62828";
async function mapPage(jobId) {
  const job = await api("GET", `/jobs/${jobId}`);
  const project = await api("GET", `/projects/${job.project_id}`);
  jobNav(job, project);
  const arts = await api("GET", `/jobs/${jobId}/artifacts`);  // listed once for the page's layers
  const [gj, pos, aerialLayer, orthoDoc, orthoUrl] = await Promise.all([layerOf(jobId, "combined/gis/cameras.geojson", arts),
    api("GET", `/projects/${job.project_id}/pos`), layerOf(jobId, "sfm/cameras.geojson", arts),
    layerOf(jobId, "views/ortho/orthophoto.json", arts), artifactUrl(jobId, "views/ortho/orthophoto.png", arts).catch(() => null)]);
  if (!gj) { main.replaceChildren(h("section", {}, h("p", {}, "no cameras layer yet: the job has not finished its combined SfM"))); return; }
  const posBy = Object.fromEntries(pos.map((r) => [r.image_name, r]));
  const pts = gj.features.map((f) => ({ p: f.properties, lon: f.geometry.coordinates[0], lat: f.geometry.coordinates[1] }));
  const ground = pts.filter((q) => q.p.set === "ground");
  const holder = h("div", { class: "map", id: "map" });
  main.replaceChildren(
    h("h1", {}, `Map of job ${jobId.slice(0, 8)}`),
    h("section", {}, h("div", { class: "legend" }, h("span", {}, h("i", { class: "dot", style: "background:#2457c5" }), "aerial, registered"),
      h("span", {}, h("i", { class: "dot", style: "background:#1a7f37" }), "ground, registered"),
      h("span", {}, h("i", { class: "dot", style: "background:#c62828" }), "ground, not registered (at its POS)"),
      h("span", {}, h("i", { class: "dot", style: "border:1px solid #98a2b3" }), "POS; arrow: POS to registered position (green within 1 m, orange 1-3 m, red farther)"),
      orthoDoc ? h("span", { class: "muted" }, "background: the survey's orthophoto (from the aerial images)") : ""), holder),
    h("section", {}, h("h2", {}, `Ground images (${ground.filter((q) => q.p.registered).length} of ${ground.length} registered)`),
      h("table", { id: "ground-images" }, h("thead", {}, h("tr", {}, h("th", {}, "image"), h("th", {}, "registered"), h("th", { class: "num" }, "to POS"), h("th", { class: "num hide-phone" }, "σ"), h("th", {}, "cause"))),
        h("tbody", {}, ground.map((q) => h("tr", { class: "ground-row" },
          h("td", {}, h("a", { href: `#/jobs/${jobId}/ground/${encodeURIComponent(q.p.name.split("/")[1])}` }, q.p.name)),
          h("td", { class: q.p.registered ? "ok" : "bad" }, q.p.registered ? "yes" : "no"),
          h("td", { class: "num" }, q.p.to_pos_m !== null ? `${q.p.to_pos_m.toFixed(2)} m` : ""),
          h("td", { class: "num hide-phone" }, q.p.position_std_m !== null ? `${q.p.position_std_m.toFixed(2)} m` : ""),
          h("td", { title: q.p.reason || "" }, q.p.cause ? h("span", { class: "cause" }, q.p.cause) : q.p.reason || "")))))));
  const L = window.L;
  if (!L) { holder.replaceChildren(h("p", { class: "bad" }, "Leaflet is missing (scripts/setup.sh installs it): the map cannot be drawn")); return; }
  // no tile server: the survey's own orthophoto is the background (the map works offline and on any network)
  const map = L.map(holder, { zoomSnap: 0.25, maxZoom: 24, attributionControl: false });
  // the view first (Leaflet draws no layer on a map without one): every POS and registered camera
  const extent = [...pts.filter((q) => q.p.registered).map((q) => [q.lat, q.lon]), ...pos.map((r) => [r.lat, r.lon])];
  if (extent.length) map.fitBounds(L.latLngBounds(extent).pad(0.1)); else map.setView([0, 0], 2);
  L.control.scale({ imperial: false, maxWidth: 160 }).addTo(map);
  const overlays = {};
  if (orthoDoc && orthoUrl) {
    const b = orthoDoc.bounds;
    overlays.orthophoto = L.imageOverlay(orthoUrl, [[b.south, b.west], [b.north, b.east]], { className: "orthophoto", alt: "orthophoto" }).addTo(map);
  }
  const prints = L.layerGroup();  // the aerial images' ground footprints (the aerial SfM's layer)
  for (const f of (aerialLayer ? aerialLayer.features : []).filter((f) => f.geometry.type === "Polygon")) {
    L.polygon(f.geometry.coordinates[0].map(([lon, lat]) => [lat, lon]), { color: "#2457c5", weight: 1, opacity: 0.4, fillOpacity: 0.04, className: "footprint", interactive: false }).addTo(prints);
  }
  if (!overlays.orthophoto) prints.addTo(map);  // without an orthophoto the footprints show the survey
  overlays["aerial footprints"] = prints;
  const cams = L.layerGroup().addTo(map);
  const colour = (q) => q.p.set === "aerial" ? "#2457c5" : q.p.registered ? "#1a7f37" : "#c62828";
  const open = (name) => () => { if (name.startsWith("ground/")) location.hash = `#/jobs/${jobId}/ground/${name.slice(7).split("/").map(encodeURIComponent).join("/")}`; };
  for (const q of pts) {
    const r = posBy[q.p.name];
    if (r) L.circleMarker([r.lat, r.lon], { radius: 5, color: "#98a2b3", weight: 1.5, fill: false, className: "pos", interactive: false }).addTo(cams);
    if (!q.p.registered) continue;
    if (r) {
      const a = [r.lat, r.lon], b = [q.lat, q.lon];
      const metres = Math.hypot((b[0] - a[0]) * 110540, (b[1] - a[1]) * 111320 * Math.cos((b[0] * Math.PI) / 180));
      const tone = offsetColour(metres);
      L.polyline([a, b], { color: tone, weight: 2, className: "error-line", interactive: false }).addTo(cams);
      const len = Math.min(1.0, 0.3 * metres);
      if (len > 0.02) L.polygon(arrowHead(a, b, len), { color: tone, weight: 1, fillOpacity: 1, className: "error-arrow", interactive: false }).addTo(cams);
    }
    const m = L.circleMarker([q.lat, q.lon], { radius: q.p.set === "ground" ? 7 : 4, color: "#fff", weight: 1, fillColor: colour(q), fillOpacity: 1, className: `cam ${q.p.set}${q.p.set === "ground" ? " link" : ""}` })
      .bindTooltip(`${q.p.name}${q.p.to_pos_m !== null ? ": " + q.p.to_pos_m.toFixed(2) + " m from its POS" : ""}`).addTo(cams);
    m.on("click", open(q.p.name));
  }
  for (const q of ground.filter((q) => !q.p.registered && posBy[q.p.name])) {
    const r = posBy[q.p.name];
    L.circleMarker([r.lat, r.lon], { radius: 7, color: "#fff", weight: 1, fillColor: "#c62828", fillOpacity: 1, className: "cam ground unregistered link" })
      .bindTooltip(`${q.p.name}: not registered${q.p.cause ? " (" + (CAUSE_WORDS[q.p.cause] || q.p.cause) + ")" : ""}`).addTo(cams).on("click", open(q.p.name));
  }
  overlays.cameras = cams;
  L.control.layers(null, overlays, { collapsed: false }).addTo(map);
}
function loadImage(url) { return new Promise((res, rej) => { const im = new Image(); im.onload = () => res(im); im.onerror = rej; im.src = url; }); }
// a match's colour: by the ground truth where the report has it (synthetic surveys), else by verification
const lineColour = (m, i, by) => {
  const flags = by === "truth" && m.truth ? m.truth : m.inliers;
  return flags ? (flags[i] ? "#22c55e" : "#ef4444") : "#facc15";
};
async function drawPair(canvas, jobId, pid, pair, by = "verification") {
  const m = await api("GET", `/jobs/${jobId}/pairs/aerial/${encodeURIComponent(pair.aerial.split("/")[1])}/ground/${encodeURIComponent(pair.ground.split("/")[1])}`);
  const [A, G] = await Promise.all([pair.aerial, pair.ground].map(async (n) => loadImage(await authedUrl(`/projects/${pid}/images/${n}/download`))));
  const k = G.height / A.height;  // the aerial image scaled to the ground image's height, side by side
  const ka = (A.width / m.aerial_size[0]) * k, kg = G.width / m.ground_size[0];  // keypoints are full-resolution pixels
  canvas.width = A.width * k + G.width; canvas.height = G.height;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(A, 0, 0, A.width * k, G.height); ctx.drawImage(G, A.width * k, 0);
  m.aerial_xy.forEach(([ax, ay], i) => {
    const [gx, gy] = m.ground_xy[i];
    ctx.strokeStyle = lineColour(m, i, by);
    ctx.beginPath(); ctx.moveTo(ax * ka, ay * ka); ctx.lineTo(A.width * k + gx * kg, gy * kg); ctx.stroke();
  });
  canvas.dataset.green = m.aerial_xy.filter((_, i) => lineColour(m, i, by) === "#22c55e").length;
  return m;
}
async function groundPage(jobId, file) {
  const job = await api("GET", `/jobs/${jobId}`);
  const project = await api("GET", `/projects/${job.project_id}`);
  jobNav(job, project);
  const name = `ground/${file}`;
  const gj = await camerasOf(jobId);
  const me = gj ? gj.features.find((f) => f.properties.name === name) : null;
  let pairs = [];
  try { pairs = (await api("GET", `/jobs/${jobId}/pairs?limit=10000`)).pairs.filter((p) => p.ground === name); }
  catch (x) { if (x.status !== 404 && x.status !== 422) throw x; }
  pairs.sort((a, b) => (b.num_inliers ?? b.num_matches) - (a.num_inliers ?? a.num_matches));
  // the intermediate views rendered for this ground image (the view planner's record, the rendered PNGs)
  const [plan, arts] = await Promise.all([layerOf(jobId, "views/views.json"), api("GET", `/jobs/${jobId}/artifacts`)]);
  // a ground-aware view names its ground image as its source; a paper view (at an aerial station) lists
  // the ground images it is matched with
  const mine = plan ? plan.views.filter((v) => v.source === name || (v.ground || []).includes(name)) : [];
  const viewImgs = await Promise.all(mine.map(async (v) => {
    const a = arts.find((x) => x.name === `views/${v.name}.png`);
    if (!a) return null;
    const src = isApiUrl(a.download_url) ? await authedUrl(a.download_url) : a.download_url;
    return h("figure", { class: "view" }, h("img", { class: "photo view-image", src, alt: v.name }), h("figcaption", { class: "muted" }, `${v.name} (${v.planner})`));
  }));
  const photo = h("img", { class: "photo", id: "ground-photo", alt: name, src: await authedUrl(`/projects/${job.project_id}/images/${name}/download`) });
  const canvas = h("canvas", { class: "matches", id: "pair-canvas" });
  const pairInfo = h("p", { class: "muted", id: "pair-info" });
  const colourBy = h("select", { id: "colour-by", onchange: () => current && show(current) },
    h("option", { value: "verification" }, "colour: verified (green) or not (red)"),
    h("option", { value: "truth" }, "colour: correct under the ground truth (green) or not (red)"));
  let current = null;
  const show = async (p) => {
    current = p;
    try {
      const m = await drawPair(canvas, jobId, job.project_id, p, colourBy.value);
      colourBy.hidden = !m.truth;
      const truth = m.truth ? `, ${m.truth.filter(Boolean).length} correct under the ground truth` : "";
      pairInfo.textContent = `${p.aerial}: ${m.num_matches} matches` + (m.inliers ? `, ${m.inliers.filter(Boolean).length} verified` : "") + truth;
    } catch (x) { pairInfo.textContent = x.message; }
  };
  const p = me ? me.properties : null;
  main.replaceChildren(
    h("h1", {}, name),
    h("section", { class: "grid2" }, photo, h("div", {}, h("h2", {}, "Pose"),
      p ? h("table", { id: "pose" }, h("tbody", {},
        h("tr", {}, h("th", {}, "registered"), h("td", { class: p.registered ? "ok" : "bad", id: "pose-registered" }, p.registered ? `yes (${p.registered_by || ""})` : "no")),
        p.cause ? h("tr", {}, h("th", {}, "cause"), h("td", { id: "pose-cause" }, p.cause)) : "",
        p.reason ? h("tr", {}, h("th", {}, "reason"), h("td", { id: "pose-reason" }, p.reason)) : "",
        p.to_pos_m !== null ? h("tr", {}, h("th", {}, "distance to its POS"), h("td", {}, `${p.to_pos_m.toFixed(2)} m`)) : "",
        p.heading !== null ? h("tr", {}, h("th", {}, "heading / pitch / roll"), h("td", {}, `${p.heading.toFixed(1)}° / ${p.pitch.toFixed(1)}° / ${p.roll.toFixed(1)}°`)) : ""))
        : h("p", { class: "muted" }, "the job has no combined model yet"))),
    h("section", {}, h("h2", {}, `Intermediate views (${viewImgs.filter(Boolean).length})`),
      h("div", { class: "grid2", id: "views" }, viewImgs.filter(Boolean))),
    h("section", {}, h("h2", {}, `Aerial images matched (${pairs.length})`),
      h("table", { id: "pairs" }, h("tbody", {}, pairs.map((q) => h("tr", { class: "pair-row" },
        h("td", {}, h("button", { class: "link", onclick: () => show(q) }, q.aerial)),
        h("td", { class: "num" }, `${q.num_matches} matches`), h("td", { class: "num" }, q.num_inliers !== null ? `${q.num_inliers} verified` : ""))))),
      colourBy, pairInfo, canvas));
  canvas.hidden = !pairs.length;
  colourBy.hidden = true;
  if (SNAP) colourBy.value = "truth";  // a static report of a synthetic survey: the truth first, where it has it
  if (pairs.length) show(pairs[0]);
}

// -- the 3D view -------------------------------------------------------------------------------------
async function artifactBytes(jobId, name) {
  const a = (await api("GET", `/jobs/${jobId}/artifacts`)).find((x) => x.name === name);
  if (!a || (SNAP && !isApiUrl(a.download_url))) return null;  // a static report links large files instead
  const r = isApiUrl(a.download_url) ? await api("GET", a.download_url, undefined, true) : await fetch(a.download_url);
  return r.arrayBuffer();
}
async function page3d(jobId) {
  const job = await api("GET", `/jobs/${jobId}`);
  const project = await api("GET", `/projects/${job.project_id}`);
  jobNav(job, project);
  const box = h("div", { id: "view3d" });
  const info = h("p", { class: "muted", id: "view3d-info" }, "loading the combined model…");
  main.replaceChildren(h("h1", {}, `3D model of job ${jobId.slice(0, 8)}`), h("section", {}, info, box,
    h("p", { class: "muted" }, "drag to turn, wheel to zoom; blue: aerial cameras, green: ground cameras (their viewing direction)")));
  const [las, opk] = await Promise.all([artifactBytes(jobId, "combined/gis/points.las"), artifactBytes(jobId, "combined/gis/cameras_opk.txt")]);
  if (!las || !opk) { info.textContent = "no combined model yet"; return; }
  let view;
  try { view = await import(SNAP ? "midview/view3d" : "./view3d.js"); }
  catch (x) { info.textContent = `the 3D library is not installed (scripts/setup.sh installs it): ${x.message}`; return; }
  const points = view.parseLas(las), cams = view.parseOpk(new TextDecoder().decode(opk));
  info.textContent = `${points.count} points, ${cams.filter((c) => c.set === "aerial").length} aerial and ${cams.filter((c) => c.set === "ground").length} ground cameras`;
  if (!view.webglAvailable()) { info.textContent += " — this browser has no WebGL to draw them"; window.midview3d = { points: points.count, cameras: cams.length, webgl: false }; return; }
  // a ground camera clicked opens its page
  const stop = view.draw(box, points, cams, (name) => {
    window.midview3dPicked = name;
    info.textContent = `${name}${name.startsWith("ground/") ? "" : " (an aerial camera)"}`;
    if (name.startsWith("ground/")) location.hash = `#/jobs/${jobId}/ground/${name.slice(7).split("/").map(encodeURIComponent).join("/")}`;
  });
  leaving.push(stop);
  window.midview3d = stop.report;
  window.midview3dScreenOf = stop.screenOf;  // where a camera is drawn (tests click it)
  // the aerial 3DGS (its Gaussians' centres and colours, in the aerial model's local frame), when it is small
  // enough to fetch
  const splatBox = h("div", { id: "splat3d" }), splatInfo = h("p", { class: "muted", id: "splat3d-info" });
  main.append(h("section", {}, h("h2", {}, "3D Gaussian Splatting model of the aerial images"), splatInfo, splatBox));
  const art = (await api("GET", `/jobs/${jobId}/artifacts`)).find((a) => a.name === "splat/point_cloud.ply");
  if (!art) { splatInfo.textContent = "no 3DGS model in this job"; return; }
  if (art.size_bytes > 64e6 || (SNAP && !isApiUrl(art.download_url))) {
    splatInfo.replaceChildren(`the 3DGS model is ${fmtBytes(art.size_bytes)}: `, h("a", { href: art.download_url }, art.name), SNAP ? " (a file beside this report)" : " (the job's results)");
    return;
  }
  const ply = view.parsePly(await artifactBytes(jobId, "splat/point_cloud.ply"));
  splatInfo.textContent = `${ply.count} of ${ply.total} Gaussians (those with opacity over 0.2), at their centres with their base colour`;
  const stopSplat = view.draw(splatBox, ply, []);
  leaving.push(stopSplat);
  window.midview3dSplat = { ...stopSplat.report, total: ply.total };
}

// -- router ----------------------------------------------------------------------------------------
async function route() {
  for (const f of leaving) f();
  leaving = [];
  document.getElementById("signout").hidden = !key || !!SNAP;
  if (!key) return signIn();
  if (SNAP && !location.hash) history.replaceState(null, "", SNAP.start);
  const parts = location.hash.replace(/^#\/?/, "").split("/").map(decodeURIComponent);
  try {
    if (parts[0] === "projects" && parts[1]) await projectPage(parts[1]);
    else if (parts[0] === "jobs" && parts[2] === "map") await mapPage(parts[1]);
    else if (parts[0] === "jobs" && parts[2] === "3d") await page3d(parts[1]);
    else if (parts[0] === "jobs" && parts[2] === "evaluation") await evaluationPage(parts[1]);
    else if (parts[0] === "jobs" && parts[2] === "ground") await groundPage(parts[1], parts.slice(3).join("/"));
    else if (parts[0] === "jobs" && parts[1]) await jobPage(parts[1]);
    else { nav.replaceChildren(h("a", { href: "#/projects" }, "projects")); await projectsPage(); }
  } catch (x) {
    if (x.status === 401) { sessionStorage.removeItem("midview-key"); key = null; return signIn(); }
    main.replaceChildren(h("section", {}, h("p", { class: "bad", id: "page-error" }, x.message)));
  }
}
document.getElementById("signout").addEventListener("click", () => { sessionStorage.removeItem("midview-key"); key = null; route(); });
window.addEventListener("hashchange", route);
route();
