// The surveys list: counts, sensor kind, reference labels, the newest job of each pipeline;
// import a survey from a server path, upload one (either with a declared sensor kind), delete
// one (reviewer).

import { api, hasRole, uploadRaw } from "../api.js";
import { ACTIVE, bytes, h, num, progressBar, statusBadge } from "../dom.js";
import { sensorBadge, sensorSelect } from "../sensors.js";

export const FORMATS = ["kitti-raw", "semantickitti", "las", "ply", "pcd", "sim"];
export const PIPELINES = [
  { kind: "run:phantom", name: "phantom" },
  { kind: "run:clutter", name: "clutter" },
  { kind: "run:guardrail", name: "guardrail" },
];

/** The newest job of a kind as a link with its status (and a bar while it runs). */
export function latestJobCell(job) {
  if (!job) return h("span", { class: "muted" }, "not run");
  return h(
    "a",
    { href: `#/jobs/${job.id}`, class: "latest-job", title: job.message },
    statusBadge(job.status),
    ACTIVE.has(job.status) ? progressBar(job, { label: false }).el : null,
  );
}

function formatSelect(id) {
  return h(
    "select",
    { id, name: "format" },
    h("option", { value: "" }, "detect"),
    FORMATS.map((f) => h("option", { value: f }, f)),
  );
}

export async function surveysView(ctx, root) {
  const user = ctx.user;
  const tableBox = h("div", { class: "table-box", id: "surveys-table" });
  root.append(
    h(
      "div",
      { class: "page-head" },
      h("h1", {}, "Surveys"),
      h("p", { class: "note" }, "Every survey the server knows, with the newest run of each pipeline."),
    ),
    h("section", { class: "card" }, tableBox),
  );
  root.append(h("div", { class: "columns" }, importForm(ctx, refresh), uploadForm(ctx, refresh)));

  let shown = "";
  async function refresh() {
    const surveys = await api("/surveys");
    const details = await Promise.all(surveys.map((sv) => api(`/surveys/${sv.id}`)));
    const signature = JSON.stringify(details);
    if (signature !== shown) {
      shown = signature;
      tableBox.replaceChildren(surveysTable(ctx, details, refresh, user));
    }
    const active = details.some((d) =>
      Object.values(d.latest_jobs || {}).some((j) => ACTIVE.has(j.status)),
    );
    return active ? 1000 : 10000;
  }
  ctx.poll(refresh);
}

function surveysTable(ctx, details, refresh, user) {
  if (!details.length) {
    return h("p", { class: "note" }, "No surveys yet: import one from the server or upload a file below.");
  }
  const canDelete = hasRole(user, "reviewer");
  const head = [
    "ID",
    "Name",
    "Format",
    "Sensor",
    "Frames",
    "Points",
    "Reference labels",
    ...PIPELINES.map((p) => p.name),
    "",
  ];
  const rows = details.map((sv) => {
    const remove = canDelete
      ? h(
          "button",
          {
            type: "button",
            class: "danger small",
            "data-action": "delete",
            onclick: (event) => deleteSurvey(ctx, event.currentTarget, sv, refresh),
          },
          "Delete",
        )
      : null;
    return h(
      "tr",
      { "data-survey": sv.id },
      h("td", {}, String(sv.id)),
      h("td", {}, h("a", { href: `#/surveys/${sv.id}`, class: "survey-link" }, sv.name)),
      h("td", {}, sv.format),
      h("td", { class: "sensor-cell" }, sensorBadge(sv.sensor_kind, sv.sensor_note)),
      h("td", { class: "num" }, num(sv.frame_count)),
      h("td", { class: "num" }, num(sv.point_count)),
      h("td", {}, sv.has_reference_labels ? "yes" : "no"),
      PIPELINES.map((p) => h("td", {}, latestJobCell(sv.latest_jobs?.[p.kind]))),
      h(
        "td",
        { class: "actions" },
        h("a", { href: `#/surveys/${sv.id}`, class: "button small" }, "Open"),
        remove,
      ),
    );
  });
  return h(
    "table",
    { class: "grid", id: "surveys" },
    h("thead", {}, h("tr", {}, head.map((x) => h("th", {}, x)))),
    h("tbody", {}, rows),
  );
}

async function deleteSurvey(ctx, button, survey, refresh) {
  const question =
    `Delete survey "${survey.name}" (${survey.id}) with its labels, decisions and models? ` +
    "Files uploaded for it are deleted too.";
  if (!window.confirm(question)) return;
  await ctx.act(button, async () => {
    await api(`/surveys/${survey.id}`, { method: "DELETE" });
    ctx.notice(`Deleted survey ${survey.name}.`);
    await refresh();
  });
}

function importForm(ctx, refresh) {
  const path = h("input", {
    id: "import-path",
    name: "path",
    required: true,
    placeholder: "e.g. surveys/drive_0005_sync",
  });
  const format = formatSelect("import-format");
  const sensor = sensorSelect("import-sensor");
  const name = h("input", { id: "import-name", name: "name", placeholder: "optional" });
  const submit = h("button", { type: "submit", class: "primary" }, "Import");
  const status = h("p", { class: "note", id: "import-status", hidden: true });
  const rootPath = h("code", { id: "import-root" }, "…");
  const rootNote = h(
    "p",
    { class: "note" },
    "A path inside the server's import root, ",
    rootPath,
    " (set by MMSCLEAN_IMPORT_ROOT).",
  );
  api("/surveys/import-root").then(
    (answer) => (rootPath.textContent = answer.path),
    (error) => ctx.error(error),
  );
  const form = h(
    "form",
    { class: "card form", id: "import-form" },
    h("h2", {}, "Import from the server"),
    rootNote,
    h("label", {}, "Path", path),
    h("div", { class: "row" }, h("label", {}, "Format", format), h("label", {}, "Name", name)),
    h("label", {}, "Sensor", sensor),
    status,
    submit,
  );
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    ctx.act(submit, async () => {
      const config = { path: path.value.trim() };
      if (format.value) config.format = format.value;
      if (sensor.value) config.sensor = sensor.value;
      if (name.value.trim()) config.name = name.value.trim();
      // a worker opens the drive (odometry can take minutes); a bad path is refused at once
      const job = await api("/jobs", { method: "POST", json: { kind: "import:survey", config } });
      form.reset();
      followImport(ctx, job, config.path, status, refresh);
    });
  });
  return form;
}

/** Show the import job's progress under the form until it ends, then list the new survey and
 * link to it there, or say why it failed. */
function followImport(ctx, job, path, status, refresh) {
  const link = h("a", { href: `#/jobs/${job.id}` }, `job ${job.id}`);
  const text = h("span");
  status.replaceChildren("Importing ", path, " (", link, "): ", text);
  status.hidden = false;
  ctx.poll(async () => {
    const j = await api(`/jobs/${job.id}`);
    if (ACTIVE.has(j.status)) {
      text.textContent = `${j.message || j.status} (${Math.round(j.progress * 100)} %)`;
      return 1000;
    }
    if (j.status === "succeeded") {
      const survey = h("a", { href: `#/surveys/${j.result.survey_id}`, id: "imported-survey" }, j.result.name);
      status.replaceChildren("Imported survey ", survey, ` (${num(j.result.frames)} frames, `, link, ").");
      ctx.notice(`Imported survey ${j.result.name} (${num(j.result.frames)} frames).`);
      await refresh();
    } else {
      status.hidden = true;
      ctx.error(new Error(`Import of ${path} ${j.status}: ${j.message}`));
    }
    return null;
  });
}

function uploadForm(ctx, refresh) {
  const file = h("input", {
    id: "upload-file",
    name: "file",
    type: "file",
    required: true,
    accept: ".las,.laz,.zip",
  });
  const format = formatSelect("upload-format");
  const sensor = sensorSelect("upload-sensor");
  const name = h("input", { id: "upload-name", name: "name", placeholder: "optional" });
  const submit = h("button", { type: "submit", class: "primary" }, "Upload");
  const fill = h("div", { class: "fill" });
  const text = h("span", { class: "progress-text" });
  const bar = h("div", { class: "progress upload", id: "upload-progress", role: "progressbar", hidden: true }, fill, text);
  const form = h(
    "form",
    { class: "card form", id: "upload-form" },
    h("h2", {}, "Upload"),
    h("p", { class: "note" }, "A .las / .laz map, or a .zip of a KITTI-raw, SemanticKITTI or simulator folder."),
    h("label", {}, "File", file),
    h("div", { class: "row" }, h("label", {}, "Format", format), h("label", {}, "Name", name)),
    h("label", {}, "Sensor", sensor),
    bar,
    submit,
  );
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    const chosen = file.files[0];
    if (!chosen) return;
    const params = new URLSearchParams({ filename: chosen.name });
    if (format.value) params.set("format", format.value);
    if (sensor.value) params.set("sensor", sensor.value);
    if (name.value.trim()) params.set("name", name.value.trim());
    bar.hidden = false;
    bar.dataset.status = "running";
    const show = (loaded, total, done) => {
      const share = total ? loaded / total : 0;
      fill.style.width = `${(share * 100).toFixed(1)}%`;
      bar.setAttribute("aria-valuenow", (share * 100).toFixed(0));
      text.textContent = done
        ? `${bytes(total)} sent; the server is reading the survey…`
        : `${bytes(loaded)} of ${bytes(total)}`;
    };
    show(0, chosen.size);
    ctx.act(submit, async () => {
      try {
        const survey = await uploadRaw(`/surveys/upload?${params}`, chosen, show);
        bar.dataset.status = "succeeded";
        text.textContent = `uploaded: ${survey.name}`;
        ctx.notice(`Uploaded survey ${survey.name} (${num(survey.frame_count)} frames).`);
        form.reset();
        await refresh();
      } catch (error) {
        bar.dataset.status = "failed";
        text.textContent = "upload failed";
        throw error;
      }
    });
  });
  return form;
}
