// The page of `autoalign label`: views with tinted masks and the instances' outlines, the
// instances' verdicts and decisions, keys to nudge. All state is the server's (GET /api/state,
// long-polled); this page only draws it and sends what the person does. Pixel coordinates sent
// are OpenCV's (the centre of the top-left pixel at 0,0) in the views' resolution.
"use strict";

const $ = (sel) => document.querySelector(sel);
let state = null;
let revision = -1;
let selected = null;          // instance number
let activeView = null;        // image id whose camera axes the keys use
const drawn = {};             // instance -> pose_revision drawn
const rowHtml = {};           // instance -> the HTML of its row in the list, as last written
let clickedAt = null;         // {job, t0, first, refined} of the last click, to time click -> outlines on screen
let shownJob = 0;
let pressedAt = null;         // where the last click began: pointer events have sub-pixel positions, clicks not
// The server's token, sent with every change: a page on another site cannot read it, so its POSTs are
// refused. From this page's HTML, then from each state (a server restarted on this port draws a new one).
let token = document.querySelector('meta[name="autoalign-token"]').content;

function status(text, error = false) {
  const el = $("#status");
  el.textContent = text;
  el.classList.toggle("error", error);
}

async function post(path, body) {
  const r = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json", "X-Autoalign-Token": token},
                               body: JSON.stringify(body || {})});
  const data = await r.json();
  if (!r.ok) { status(data.error || `${path}: ${r.status}`, true); return null; }
  return data;
}

function colourOf(index) {
  const order = state.instances.map((i) => i.index);
  return state.colours[order.indexOf(index) % state.colours.length];
}

function buildViews() {
  const grid = $("#views");
  for (const v of state.views) {
    const div = document.createElement("div");
    div.className = "view";
    div.dataset.imageId = v.image_id;
    div.style.aspectRatio = `${v.width} / ${v.height}`;   // laid out before the photo arrives
    div.innerHTML = `<img class="photo" alt="view ${v.image_id}" src="/api/view/${v.image_id}.jpg">` +
      `<img class="tint" alt="" src="/api/tint/${v.image_id}.png">` +
      `<svg viewBox="-0.5 -0.5 ${v.width} ${v.height}" preserveAspectRatio="none"></svg>` +
      `<span class="name">im ${v.image_id}</span>`;
    div.addEventListener("mouseenter", () => setActive(v.image_id));
    const tint = div.querySelector("img.tint");
    tint.addEventListener("pointerdown", (e) => { pressedAt = [e.clientX, e.clientY]; });
    tint.addEventListener("click", (e) => clickView(e, v));
    grid.appendChild(div);
  }
  const sel = $("#object");
  for (const o of state.objects) {
    const opt = document.createElement("option");
    opt.value = o.obj_id;
    opt.textContent = `obj ${o.obj_id}` + (o.diameter ? ` (${Math.round(o.diameter)} mm)` : "");
    sel.appendChild(opt);
  }
  if (state.viewer_url) {   // loaded when first opened: its WebGL drawing costs CPU where there is no GPU
    const box = $("#viewer-box");
    box.hidden = false;
    box.addEventListener("toggle", () => { if (box.open && !$("#viewer").src) $("#viewer").src = state.viewer_url; });
  }
}

function setActive(imageId) {
  activeView = imageId;
  for (const d of document.querySelectorAll(".view")) d.classList.toggle("active", +d.dataset.imageId === imageId);
}

async function clickView(e, v) {
  const r = e.target.getBoundingClientRect();
  const [cx, cy] = pressedAt || [e.clientX, e.clientY];
  const u = (cx - r.left) * v.width / r.width - 0.5;   // OpenCV: pixel centres at integers
  const y = (cy - r.top) * v.height / r.height - 0.5;
  setActive(v.image_id);
  const obj = +$("#object").value;
  const t0 = performance.now();
  status(`placing obj ${obj}…`);
  const reply = await post("/api/place", {obj_id: obj, image_id: v.image_id, u: u, v: y});
  if (reply) clickedAt = {job: reply.job, t0: t0, first: false, refined: false};
}

function instanceRow(inst) {
  const div = document.createElement("div");
  div.className = "instance";
  div.dataset.index = inst.index;
  div.style.setProperty("--colour", colourOf(inst.index));
  div.addEventListener("click", () => select(inst.index));
  return div;
}

function fmt(xs, unit) { return xs ? xs.map((x) => x.toFixed(x < 1 ? 2 : 1)).join("/") + " " + unit : "–"; }

function renderInstances() {
  const box = $("#instances");
  for (const inst of state.instances) {
    let div = box.querySelector(`.instance[data-index="${inst.index}"]`);
    if (!div) { div = instanceRow(inst); box.appendChild(div); }
    div.classList.toggle("selected", inst.index === selected);
    div.dataset.decision = inst.decision;
    div.dataset.verdict = inst.verdict || "";
    const suggested = inst.suggested_obj_id != null && !inst.obj_id ? ` (scene says obj ${inst.suggested_obj_id})` : "";
    const placed = inst.obj_id != null && inst.T_wm;
    const html = `<div class="row"><strong>instance ${inst.index}</strong>` +
      (placed ? `obj ${inst.obj_id}` : `not placed${suggested}`) +
      `<span class="badge decision ${inst.decision}">${inst.decision}</span>` +
      (inst.verdict ? `<span class="badge verdict ${inst.verdict}">${inst.verdict}</span>` : "") +
      (inst.symmetric ? `<span class="badge">symmetric</span>` : "") + `</div>` +
      (placed ? `<div class="row">IoU ${inst.median_iou != null ? inst.median_iou.toFixed(3) : "–"} · ` +
        (inst.verdict === "ok" ? `σ ${fmt(inst.sigma_mm, "mm")} ${fmt(inst.sigma_deg, "°")}`
          : `<span class="no-sigma" title="a sigma is the precision of a trusted pose only">σ not shown (${inst.verdict || "not judged"})</span>`) +
        ` · worst views ` +
        inst.worst_views.map((w) => `<a href="#" data-view="${w}">${w}</a>`).join(" ") + `</div>` +
        `<div class="reasons">${inst.reasons.join("; ")}</div>` +
        `<div class="row"><button data-act="refine">refine from here</button>` +
        `<button data-act="accept">accept</button><button data-act="reject">reject</button>` +
        `<label><input type="checkbox" data-act="symmetric"${inst.symmetric ? " checked" : ""}> symmetric</label></div>`
        : "");
    // Rewritten only when its content changed: every change of the session (another instance, another
    // tab, a job's progress) redraws the list, and a click whose button is replaced under it is lost.
    if (rowHtml[inst.index] !== html) {
      rowHtml[inst.index] = html;
      div.innerHTML = html;
      for (const b of div.querySelectorAll("[data-act]")) {
        b.addEventListener("click", (e) => { e.stopPropagation(); act(inst.index, b.dataset.act, b); });
      }
      for (const a of div.querySelectorAll("a[data-view]")) {
        a.addEventListener("click", (e) => {
          e.preventDefault(); e.stopPropagation();
          const v = document.querySelector(`.view[data-image-id="${a.dataset.view}"]`);
          v.scrollIntoView({block: "center"}); setActive(+a.dataset.view);
        });
      }
    }
    for (const b of div.querySelectorAll("[data-act]")) b.disabled = state.job.running && b.dataset.act === "refine";
    const sym = div.querySelector('input[data-act="symmetric"]');
    if (sym) sym.checked = !!inst.symmetric;   // the server's, also where a toggle was refused
  }
}

function select(index) {
  if (selected !== index) post("/api/focus", {instance: index});   // the 3D view's gizmo follows
  selected = index;
  for (const d of document.querySelectorAll(".instance")) d.classList.toggle("selected", +d.dataset.index === index);
}

async function act(index, what, el) {
  select(index);
  if (what === "refine") {
    clickedAt = null;
    if (await post("/api/refine", {instance: index})) status(`refining instance ${index}…`);
  } else if (what === "accept" || what === "reject") {
    await post("/api/decide", {instance: index, decision: what === "accept" ? "accepted" : "rejected"});
  } else if (what === "symmetric") {
    await post("/api/symmetric", {instance: index, symmetric: el.checked});
  }
}

async function drawContours() {
  for (const inst of state.instances) {
    if (inst.obj_id == null || !inst.T_wm || drawn[inst.index] === inst.pose_revision) continue;
    const r = await fetch(`/api/contours/${inst.index}`);
    const data = await r.json();
    if (!r.ok) { status(data.error, true); continue; }
    const colour = colourOf(inst.index);
    for (const view of document.querySelectorAll(".view")) {
      const svg = view.querySelector("svg");
      for (const old of svg.querySelectorAll(`polyline[data-instance="${inst.index}"]`)) old.remove();
      for (const poly of data.contours[view.dataset.imageId] || []) {
        const el = document.createElementNS("http://www.w3.org/2000/svg", "polyline");
        el.setAttribute("points", poly.concat([poly[0]]).map((p) => p.join(",")).join(" "));
        el.setAttribute("stroke", colour);
        el.classList.toggle("searched", inst.source === "search");   // dashed until refined
        el.dataset.instance = inst.index;
        svg.appendChild(el);
      }
    }
    drawn[inst.index] = data.pose_revision;
  }
  document.body.dataset.drawn = Object.entries(drawn).map(([k, v]) => `${k}:${v}`).join(",");
}

function showJob() {
  const j = state.job;
  if (!j.number) { status(`${state.instances.length} instances in ${state.views.length} views`); return; }
  if (j.running) { status(`${j.kind}${j.instance != null ? " instance " + j.instance : ""}: ${j.stage}` +
                          (j.total ? ` ${j.done}/${j.total}` : "") + ` (${j.seconds.toFixed(1)} s)`); return; }
  if (j.error) { if (shownJob !== j.number) status(`${j.kind} failed: ${j.error}`, true); }
  else if (j.kind === "export") status(`exported to ${state.out_dir}/bop`);
  else status(`${j.kind}${j.instance != null ? " instance " + j.instance : ""}: done in ${j.seconds.toFixed(1)} s`);
  shownJob = j.number;
}

async function apply(s) {
  const first = state === null;
  state = s;
  revision = s.revision;
  if (s.token) token = s.token;
  if (first) buildViews();
  renderInstances();
  showJob();
  await drawContours();
  const j = s.job;
  const clicked = clickedAt && clickedAt.job === j.number && j.instance != null ?
    s.instances.find((i) => i.index === j.instance) : null;
  const shownOnly = clicked && (clicked.source === "search" || clicked.source === "refining");
  if (clicked && !clickedAt.first && drawn[j.instance] === clicked.pose_revision &&
      (shownOnly || (!j.running && !j.error))) {
    // the first outlines of this click: the orientation search's pose (dashed), or a refined one
    const t0 = clickedAt.t0;
    clickedAt.first = true;
    requestAnimationFrame(() => requestAnimationFrame(() => {
      document.body.dataset.clickToFirstOutlinesMs = (performance.now() - t0).toFixed(0);
    }));
  }
  if (clicked && !clickedAt.refined && drawn[j.instance] === clicked.pose_revision &&
      (clicked.source === "refining" || (!j.running && !j.error))) {
    // the first refined pose of this click, before its uncertainty and verdict (or with them)
    const t0 = clickedAt.t0;
    clickedAt.refined = true;
    requestAnimationFrame(() => requestAnimationFrame(() => {
      document.body.dataset.clickToRefinedPoseMs = (performance.now() - t0).toFixed(0);
    }));
  }
  if (clickedAt && clickedAt.job === j.number && !j.running && !j.error && j.instance != null &&
      drawn[j.instance] !== undefined) {
    const t0 = clickedAt.t0;
    clickedAt = null;
    if (selected === null || selected !== j.instance) select(j.instance);
    requestAnimationFrame(() => requestAnimationFrame(() => {   // after the outlines were painted
      window.clickToContoursMs = performance.now() - t0;
      document.body.dataset.clickToContoursMs = window.clickToContoursMs.toFixed(0);
      status(`placed instance ${j.instance}: outlines on screen ${(window.clickToContoursMs / 1000).toFixed(1)} s ` +
             `after the click`);
    }));
  }
}

async function poll() {
  for (;;) {
    try {
      const r = await fetch(`/api/state?since=${revision}`);
      if (!r.ok) throw new Error(`state: ${r.status}`);
      await apply(await r.json());
    } catch (e) {
      status(`lost the server (${e.message}); retrying…`, true);
      await new Promise((ok) => setTimeout(ok, 1000));
    }
  }
}

const KEY_MOVES = {   // key -> [move_mm, turn_deg] in the active view's camera axes
  ArrowRight: [[1, 0, 0], [0, 0, 0]], ArrowLeft: [[-1, 0, 0], [0, 0, 0]],
  ArrowDown: [[0, 1, 0], [0, 0, 0]], ArrowUp: [[0, -1, 0], [0, 0, 0]],
  PageUp: [[0, 0, 1], [0, 0, 0]], PageDown: [[0, 0, -1], [0, 0, 0]],
  q: [[0, 0, 0], [0, 0, -1]], e: [[0, 0, 0], [0, 0, 1]], w: [[0, 0, 0], [1, 0, 0]], s: [[0, 0, 0], [-1, 0, 0]],
  a: [[0, 0, 0], [0, -1, 0]], d: [[0, 0, 0], [0, 1, 0]],
};

document.addEventListener("keydown", async (e) => {
  if (selected === null || e.target.tagName === "SELECT" || e.target.tagName === "INPUT") return;
  const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
  if (key === "r") { e.preventDefault(); return act(selected, "refine"); }
  if (key === "z" && (e.ctrlKey || e.metaKey)) { e.preventDefault(); return post("/api/undo", {instance: selected}); }
  if (key === "Enter") { e.preventDefault(); return act(selected, "accept"); }
  if (key === "Delete") { e.preventDefault(); return act(selected, "reject"); }
  const m = KEY_MOVES[key];
  if (!m) return;
  e.preventDefault();
  const view = activeView !== null ? activeView : state.views[0].image_id;
  const f = e.shiftKey ? 5 : 1;
  await post("/api/nudge", {instance: selected, image_id: view, move_mm: m[0].map((x) => x * f),
                            turn_deg: m[1].map((x) => x * f)});
});

$("#tile").addEventListener("input", (e) => $("#views").style.setProperty("--tile", `${e.target.value}px`));

$("#refine-all").addEventListener("click", async () => {
  if (await post("/api/refine_all", {})) status("refining all together…");
});

$("#export").addEventListener("click", async () => {
  if (await post("/api/export", {})) status("exporting…");
});

poll();
