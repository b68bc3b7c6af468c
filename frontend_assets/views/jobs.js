// Jobs: the list with live progress bars (polled every second while any job is queued or
// running), cancel / resume / requeue, and one job's details: log tail, result files, metrics.

import { api, hasRole } from "../api.js";
import {
  ACTIVE,
  bytes,
  duration,
  facts,
  h,
  note,
  num,
  progressBar,
  section,
  statusBadge,
  when,
} from "../dom.js";
import { keyValueTable, pipelineOf, renderMetrics } from "../metrics.js";

const STATUSES = ["queued", "running", "succeeded", "failed", "cancelled", "interrupted"];
const KINDS = [
  "run:phantom",
  "run:clutter",
  "run:guardrail",
  "clutter:recompute",
  "guardrail:rebuild",
  "train:phantom",
  "train:guardrail",
];
const LOG_LINES = 200;

/** May USER cancel or resume JOB? (the server's rule: training needs an admin; others' jobs a
 * reviewer). */
function mayControl(user, job) {
  if (job.kind.startsWith("train:") && !hasRole(user, "admin")) return false;
  return job.created_by === user.id || hasRole(user, "reviewer");
}

function mayStart(user, kind) {
  return !kind.startsWith("train:") || hasRole(user, "admin");
}

/** The buttons for what USER may do with JOB now. */
function jobActions(ctx, job, onChange) {
  const user = ctx.user;
  const buttons = [];
  const post = (action, label, cls) =>
    h(
      "button",
      {
        type: "button",
        class: `small ${cls}`,
        "data-action": action,
        "data-job": job.id,
        onclick: (event) =>
          ctx.act(event.currentTarget, async () => {
            const answer = await api(`/jobs/${job.id}/${action}`, { method: "POST" });
            const what = action === "requeue" ? `queued again as job ${answer.id}` : `${action}: ${answer.status}`;
            ctx.notice(`Job ${job.id} ${what}.`);
            await onChange(answer);
          }),
      },
      label,
    );
  if (mayControl(user, job)) {
    if (ACTIVE.has(job.status) && !job.cancel_requested) buttons.push(post("cancel", "Cancel", "danger"));
    if (["interrupted", "failed", "cancelled"].includes(job.status)) {
      buttons.push(post("resume", "Resume", ""));
    }
  }
  if (!ACTIVE.has(job.status) && mayStart(user, job.kind)) buttons.push(post("requeue", "Run again", ""));
  if (job.cancel_requested && ACTIVE.has(job.status)) {
    buttons.push(h("span", { class: "muted" }, "cancelling…"));
  }
  return buttons;
}

function who(ctx, users, id) {
  if (id === null || id === undefined) return "system";
  if (id === ctx.user.id) return "you";
  return users.get(id) || `user ${id}`;
}

async function userNames(ctx) {
  // only admins may list users; everyone else sees "you" or a user id
  if (!hasRole(ctx.user, "admin")) return new Map();
  try {
    return new Map((await api("/users")).map((u) => [u.id, u.username]));
  } catch {
    return new Map();
  }
}

async function surveyNames() {
  return new Map((await api("/surveys")).map((sv) => [sv.id, sv.name]));
}

function surveyLink(surveys, id) {
  if (id === null || id === undefined) return h("span", { class: "muted" }, "–");
  return h("a", { href: `#/surveys/${id}` }, surveys.get(id) || `survey ${id}`);
}

/** A table row for a job that patches itself in place, so buttons do not jump while the bar
 * moves. */
function jobRow(ctx, job, lookups, refresh) {
  const bar = progressBar(job);
  const status = h("td", {});
  const message = h("div", { class: "job-message" });
  const time = h("td", { class: "num" });
  const actions = h("td", { class: "actions" });
  const el = h(
    "tr",
    { "data-job": job.id },
    h("td", {}, h("a", { href: `#/jobs/${job.id}` }, String(job.id))),
    h("td", {}, job.kind),
    h("td", {}, surveyLink(lookups.surveys, job.survey_id)),
    status,
    h("td", { class: "progress-cell" }, bar.el, message),
    h("td", {}, when(job.created_at)),
    time,
    h("td", {}, who(ctx, lookups.users, job.created_by)),
    actions,
  );
  let actionKey = "";
  const update = (j) => {
    bar.set(j);
    status.replaceChildren(statusBadge(j.status));
    message.textContent = j.message;
    message.title = j.message;
    time.textContent = duration(j.seconds);
    const key = `${j.status}/${j.cancel_requested}`;
    if (key !== actionKey) {
      actionKey = key;
      const results = h("a", { href: `#/jobs/${j.id}`, class: "button small" }, "Results");
      actions.replaceChildren(...jobActions(ctx, j, refresh), ...(j.status === "succeeded" ? [results] : []));
    }
  };
  update(job);
  return { el, update };
}

export async function jobsView(ctx, root) {
  const statusFilter = h(
    "select",
    { id: "filter-status" },
    h("option", { value: "" }, "any status"),
    STATUSES.map((x) => h("option", { value: x }, x)),
  );
  const kindFilter = h(
    "select",
    { id: "filter-kind" },
    h("option", { value: "" }, "any kind"),
    KINDS.map((x) => h("option", { value: x }, x)),
  );
  const surveyId = ctx.query.get("survey");
  const [surveys, users] = await Promise.all([surveyNames(), userNames(ctx)]);
  const tbody = h("tbody");
  const empty = note("No jobs match.");
  empty.hidden = true;
  root.append(
    h(
      "div",
      { class: "page-head" },
      h("h1", {}, "Jobs"),
      h(
        "div",
        { class: "filters" },
        statusFilter,
        kindFilter,
        surveyId
          ? h("span", { class: "chip" }, `survey: ${surveys.get(Number(surveyId)) || surveyId} `, h("a", { href: "#/jobs" }, "×"))
          : null,
      ),
    ),
    h(
      "section",
      { class: "card" },
      h(
        "table",
        { class: "grid", id: "jobs" },
        h(
          "thead",
          {},
          h(
            "tr",
            {},
            ["ID", "Kind", "Survey", "Status", "Progress", "Created", "Run time", "By", ""].map((x) => h("th", {}, x)),
          ),
        ),
        tbody,
      ),
      empty,
    ),
  );

  const rows = new Map();
  const lookups = { surveys, users };
  let poller = null;
  const changed = async () => poller?.now();
  async function refresh() {
    const params = new URLSearchParams({ limit: 100 });
    if (statusFilter.value) params.set("status", statusFilter.value);
    if (kindFilter.value) params.set("kind", kindFilter.value);
    if (surveyId) params.set("survey_id", surveyId);
    const jobs = await api(`/jobs?${params}`);
    const seen = new Set();
    jobs.forEach((job, index) => {
      seen.add(job.id);
      let row = rows.get(job.id);
      if (!row) {
        if (job.survey_id !== null && !surveys.has(job.survey_id)) surveys.set(job.survey_id, null);
        row = jobRow(ctx, job, lookups, changed);
        rows.set(job.id, row);
      } else {
        row.update(job);
      }
      if (tbody.children[index] !== row.el) tbody.insertBefore(row.el, tbody.children[index] || null);
    });
    for (const [id, row] of rows) {
      if (!seen.has(id)) {
        row.el.remove();
        rows.delete(id);
      }
    }
    empty.hidden = jobs.length > 0;
    return jobs.some((j) => ACTIVE.has(j.status)) ? 1000 : 5000;
  }
  const refilter = () => {
    for (const row of rows.values()) row.el.remove();
    rows.clear();
    poller.now();
  };
  statusFilter.addEventListener("change", refilter);
  kindFilter.addEventListener("change", refilter);
  poller = ctx.poll(refresh);
}

// --- one job --------------------------------------------------------------------------------

function filesList(jobId, files) {
  if (!files.length) return note("This job wrote no files (yet).");
  // folders with many files (labels/ holds one per frame) fold away
  const groups = new Map();
  for (const f of files) {
    const slash = f.name.indexOf("/");
    const folder = slash > 0 ? f.name.slice(0, slash) : "";
    if (!groups.has(folder)) groups.set(folder, []);
    groups.get(folder).push(f);
  }
  const link = (f) =>
    h(
      "li",
      {},
      h("a", { href: `/jobs/${jobId}/files/${f.name.split("/").map(encodeURIComponent).join("/")}`, download: "" }, f.name),
      h("span", { class: "muted" }, ` ${bytes(f.size)}`),
    );
  const parts = [];
  for (const [folder, list] of groups) {
    if (!folder || list.length <= 5) {
      parts.push(h("ul", { class: "files" }, list.map(link)));
    } else {
      const size = list.reduce((a, f) => a + f.size, 0);
      parts.push(
        h(
          "details",
          { class: "files-folder" },
          h("summary", {}, `${folder}/ (${num(list.length)} files, ${bytes(size)})`),
          h("ul", { class: "files" }, list.map(link)),
        ),
      );
    }
  }
  return h("div", { id: "job-files" }, parts);
}

export async function jobView(ctx, root, id) {
  const [job, surveys, users] = await Promise.all([api(`/jobs/${id}`), surveyNames(), userNames(ctx)]);
  const lookups = { surveys, users };
  const bar = progressBar(job);
  const status = h("span");
  const message = h("p", { class: "job-message wide" });
  const actions = h("div", { class: "actions" });
  const details = h("div");
  const log = h("pre", { class: "log", id: "job-log" });
  const body = h("div");
  root.append(
    h(
      "div",
      { class: "page-head" },
      h("p", { class: "crumbs" }, h("a", { href: "#/jobs" }, "Jobs"), ` / job ${job.id}`),
      h("h1", {}, `Job ${job.id}: ${job.kind}`),
    ),
    h(
      "section",
      { class: "card", id: "job-status" },
      h("div", { class: "status-line" }, status, bar.el, actions),
      message,
      details,
    ),
    body,
    section(
      "Log",
      h(
        "p",
        { class: "note" },
        `The last ${LOG_LINES} lines, refreshed while the job runs. `,
        h("a", { href: `/jobs/${job.id}/log`, target: "_blank", rel: "noopener" }, "Whole log"),
      ),
      log,
    ),
  );

  let shownStatus = null;
  let actionKey = "";
  async function show(j) {
    bar.set(j);
    status.replaceChildren(statusBadge(j.status));
    message.textContent = j.message;
    const rows = [
      ["survey", surveyLink(lookups.surveys, j.survey_id)],
      ["started by", who(ctx, lookups.users, j.created_by)],
      ["created", when(j.created_at)],
      ["started", when(j.started_at)],
      ["finished", when(j.finished_at)],
      ["run time", duration(j.seconds)],
      ["attempts", num(j.attempts)],
      ["config", h("code", {}, JSON.stringify(j.config))],
    ];
    details.replaceChildren(facts(rows, { wide: true }));
    const key = `${j.status}/${j.cancel_requested}`;
    if (key !== actionKey) {
      actionKey = key;
      actions.replaceChildren(
        ...jobActions(ctx, j, async (answer) => {
          if (answer.id !== j.id) location.hash = `#/jobs/${answer.id}`;
          else poller.now();
        }),
      );
    }
    if (j.status !== shownStatus) {
      shownStatus = j.status;
      body.replaceChildren(...(await resultSections(j)));
    }
  }

  async function resultSections(j) {
    if (ACTIVE.has(j.status)) return [];
    const results = await api(`/jobs/${j.id}/results`);
    const parts = [];
    const pipeline = pipelineOf(j.kind);
    const result = j.result || {};
    if (j.status === "succeeded" && j.kind.startsWith("run:")) {
      parts.push(
        h("section", { class: "card", id: "job-metrics" }, h("h2", {}, "Metrics"), renderMetrics(pipeline, result.metrics)),
      );
    }
    if (j.kind.startsWith("train:") && result.model_version_id !== undefined) {
      parts.push(section("Model", h("p", {}, "The version this training made is on the ", h("a", { href: "#/models" }, "models page"), ".")));
    }
    if (j.kind === "import:survey" && result.survey_id !== undefined) {
      const survey = h("a", { href: `#/surveys/${result.survey_id}`, id: "job-survey" }, result.name);
      parts.push(section("Survey", h("p", {}, "This import registered the survey ", survey, ` (${num(result.frames)} frames).`)));
    }
    const tables = [];
    if (result.counts) tables.push(h("div", {}, h("h3", {}, "Counts"), keyValueTable(result.counts)));
    if (result.timings) tables.push(h("div", {}, h("h3", {}, "Timings"), keyValueTable(result.timings, { unit: "s" })));
    if (tables.length) parts.push(section("Summary", h("div", { class: "columns" }, tables)));
    parts.push(section("Result files", filesList(j.id, results.files)));
    return parts;
  }

  async function refresh() {
    const [j, text] = await Promise.all([api(`/jobs/${id}`), api(`/jobs/${id}/log?tail=${LOG_LINES}`)]);
    await show(j);
    const atBottom = log.scrollTop + log.clientHeight >= log.scrollHeight - 4;
    log.textContent = text || "(no log yet: the job has not started)";
    if (atBottom) log.scrollTop = log.scrollHeight; // follow the tail unless the user scrolled up
    return ACTIVE.has(j.status) ? 1000 : 5000; // slowly after the end: it may be resumed
  }
  const poller = ctx.poll(refresh);
}
