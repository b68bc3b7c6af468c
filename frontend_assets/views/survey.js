// One survey: its sensor kind (declared here when unknown), start its pipelines, open the
// viewer modes, see the review state (pillar labels, clutter decisions, guardrail models), its
// work areas (views/areas.js), download exports (with a warning while review is pending); and
// its metrics page.

import { api, hasRole } from "../api.js";
import {
  ACTIVE,
  duration,
  facts,
  h,
  note,
  num,
  progressBar,
  section,
  shareBar,
  statusBadge,
  table,
  when,
} from "../dom.js";
import { modelHeadline, pipelineOf, renderMetrics } from "../metrics.js";
import { bars, figure } from "../plots.js";
import { sensorBlock } from "../sensors.js";
import { readinessLine, workAreasBlock } from "./areas.js";

// The options a run job takes that people change; everything else stays the paper's default.
const PIPELINE_FORMS = [
  {
    kind: "run:clutter",
    title: "Clutter removal",
    paper: "Lee et al., Sensors 2020: camera masks, free space and tracking per frame",
    options: [
      { key: "mode", label: "Remove", type: "select", choices: ["clutter", "dynamic"], default: "clutter" },
      { key: "use_camera", label: "camera masks", type: "checkbox", default: true, needs: "segmentation" },
      { key: "use_free_space", label: "free space", type: "checkbox", default: true },
      { key: "use_tracking", label: "tracking", type: "checkbox", default: true },
      { key: "expansion", label: "Mask expansion", type: "select", choices: ["cluster", "pad"], default: "cluster" },
      { key: "mask_padding_px", label: "Mask padding [px]", type: "number", step: 1, min: 0, max: 200, default: 30 },
    ],
  },
  {
    kind: "run:phantom",
    title: "Phantom removal",
    paper: "Nagy & Benedek: 3D CNN on pillar neighbourhoods of the accumulated map",
    options: [
      { key: "refine", label: "5x5 neighbourhood vote", type: "checkbox", default: true },
      { key: "dense", label: "dense tiled inference", type: "checkbox", default: true },
      { key: "model_id", label: "Model", type: "model", pipeline: "phantom", default: "" },
    ],
  },
  {
    kind: "run:guardrail",
    title: "Guardrail extraction",
    paper: "Matsumoto, Mori, Masuda: slice classification and shape reconstruction",
    options: [
      // "" leaves the choice to the classifier version's card (default_head: geometry-only for
      // rotating scanners, whose real crops do not look like rendered ones)
      { key: "head", label: "Classifier", type: "select", choices: [["", "the model's default"], "image+geometry", "image", "geometry"], default: "" },
      { key: "threshold", label: "Threshold", type: "number", step: 0.05, min: 0.05, max: 0.95, default: "", placeholder: "the model's" },
      { key: "spacing", label: "Slice length [m]", type: "number", step: 0.1, min: 0.1, max: 5, default: 0.5 },
      { key: "reconstruct", label: "reconstruct models", type: "checkbox", default: true },
      { key: "model_id", label: "Classifier version", type: "model", pipeline: "guardrail", default: "" },
    ],
  },
];

const VIEWER_MODES = [
  { mode: "pillars", title: "Pillar labelling", text: "label ground / high / short / phantom pillars" },
  { mode: "clutter", title: "Clutter review", text: "approve or reject removed objects per frame" },
  { mode: "guardrails", title: "Guardrail review", text: "correct slice labels" },
  { mode: "models", title: "Model inspection", text: "accept or reject reconstructed guardrails" },
  { mode: "qa", title: "QA", text: "original vs cleaned map, removed points" },
];

// `maps`: the run's maps an export is made of (any of them will do)
const EXPORTS = [
  { file: "cleaned.laz", text: "cleaned map (LAZ)", needs: "removal", maps: ["cleaned"] },
  { file: "removed.laz", text: "removed points (LAZ)", needs: "removal", maps: ["removed"] },
  {
    file: "classified.laz",
    text: "classified map, ASPRS classes (LAZ)",
    needs: "removal",
    maps: ["cleaned", "removed"],
  },
  {
    file: "cleaned.laz?source=combined",
    text: "cleaned map, clutter and phantom combined (LAZ)",
    needs: "combined",
  },
  {
    file: "removed.laz?source=combined",
    text: "removed points, clutter and phantom combined (LAZ)",
    needs: "combined",
  },
  { file: "cleaned.pcd", text: "cleaned map (PCD)", needs: "removal", maps: ["cleaned"] },
  { file: "map.pcd", text: "map with labels (PCD)", needs: "removal", maps: ["cleaned", "removed"] },
  { file: "semantickitti-labels.zip", text: "SemanticKITTI labels per frame (zip)", needs: "clutter" },
  { file: "guardrails.zip?format=glb", text: "approved guardrails (glTF)", needs: "guardrails" },
  { file: "guardrails.zip?format=obj", text: "approved guardrails (OBJ)", needs: "guardrails" },
  { file: "pillars.csv", text: "pillar labels (CSV)", needs: "pillars" },
  { file: "pillars.npz", text: "pillar labels (NumPy)", needs: "pillars" },
  { file: "qa-report.html", text: "QA report (HTML)", open: true },
];

const CLUTTER_KINDS = ["run:clutter", "clutter:recompute"];
const REMOVAL_KINDS = [...CLUTTER_KINDS, "run:phantom"]; // the runs that write cleaned maps

function pageHead(survey, tab) {
  return h(
    "div",
    { class: "page-head" },
    h("p", { class: "crumbs" }, h("a", { href: "#/surveys" }, "Surveys"), " / ", survey.name),
    h("h1", {}, survey.name),
    h(
      "nav",
      { class: "tabs" },
      h("a", { href: `#/surveys/${survey.id}`, class: tab === "overview" ? "active" : "" }, "Overview"),
      h(
        "a",
        { href: `#/surveys/${survey.id}/metrics`, class: tab === "metrics" ? "active" : "", id: "metrics-tab" },
        "Metrics",
      ),
      h("a", { href: `#/jobs?survey=${survey.id}` }, "Jobs"),
    ),
  );
}

function surveyFacts(sv) {
  const f = sv.frames || {};
  const rows = [
    ["format", sv.format],
    ["frames", num(sv.frame_count)],
    ["points", num(sv.point_count)],
    ["duration", f.duration_s !== undefined ? duration(f.duration_s) : ""],
    ["trajectory", f.trajectory_length_m !== undefined ? `${num(f.trajectory_length_m, 1)} m` : ""],
    ["reference labels", sv.has_reference_labels ? "yes" : "no"],
    ["poses", sv.poses_estimated ? "estimated (LiDAR odometry)" : "from the survey"],
    ["registered", when(sv.created_at)],
    ["source", h("code", {}, sv.source_path)],
  ];
  return facts(rows, { wide: true });
}

// --- pipelines ------------------------------------------------------------------------------

function optionInput(kind, option) {
  const id = `opt-${kind.replace(":", "-")}-${option.key}`;
  if (option.type === "checkbox") {
    const input = h("input", { type: "checkbox", id, name: option.key, checked: option.default });
    const el = h("label", { class: "check" }, input, option.label);
    if (option.needs === "segmentation") whenWeightsMissing(input, el);
    return { input, el };
  }
  let input;
  if (option.type === "model") {
    // a model version of the registry by id (jobs never name a checkpoint file)
    const promoted = h("option", { value: "" }, "promoted version for this survey's scanner");
    input = h("select", { id, name: option.key }, promoted);
    api(`/models?${new URLSearchParams({ pipeline: option.pipeline })}`)
      .then((models) => {
        // each version with the scanner kind it was trained for and its held-out F, so a
        // rotating survey is not run with a profile-scanner model by mistake
        input.append(...models.map((m) => h("option", { value: String(m.id), "data-sensor": m.sensor_kind }, modelChoice(m))));
      })
      .catch(() => {}); // the promoted version stays available
  } else if (option.type === "select") {
    input = h(
      "select",
      { id, name: option.key },
      option.choices.map((choice) => {
        const [value, text] = Array.isArray(choice) ? choice : [choice, choice];
        return h("option", { value, selected: value === option.default }, text);
      }),
    );
  } else {
    input = h("input", {
      id,
      name: option.key,
      type: option.type,
      step: option.step,
      min: option.min,
      max: option.max,
      value: String(option.default),
      placeholder: option.placeholder,
    });
  }
  return { input, el: h("label", {}, option.label, input) };
}

function modelChoice(m) {
  const { f1 } = modelHeadline(m);
  const score = typeof f1 === "number" ? `, F ${f1.toFixed(1)} %` : "";
  return `${m.id}: ${m.name} (${m.sensor_kind} scanners${score}${m.is_promoted ? ", promoted" : ""})`;
}

/** The camera masks need the ESPNetv2 weights on the server (never downloaded at run time):
 * without them the option is unticked and says where to get them, instead of a failed job. */
function whenWeightsMissing(input, label) {
  api("/models/segmentation")
    .then((weights) => {
      if (weights.available) return;
      input.checked = false;
      const where = h("code", {}, weights.file);
      label.after(
        h(
          "p",
          { class: "note", id: `${input.id}-missing` },
          "The image segmentation weights are missing on this server: put them at ",
          where,
          ` (from ${weights.upstream}; MMSCLEAN_WEIGHTS_DIR names their folder). `,
          "Without them the run uses free space and tracking.",
        ),
      );
    })
    .catch(() => {}); // the option stays as it is; a failed run names the missing file
}

/** The options that differ from the defaults (the server fills in the rest). */
function configOf(form, inputs) {
  const config = {};
  for (const option of form.options) {
    const input = inputs[option.key];
    let value;
    if (option.type === "checkbox") value = input.checked;
    else if (option.type === "number") {
      if (!input.value.trim()) continue; // unset: the server's (or the model's) default
      value = Number(input.value);
    }
    else value = input.value.trim();
    if (option.type !== "checkbox" && option.type !== "number" && !value) continue; // unset
    if (option.type === "model") value = Number(value);
    if (value !== option.default) config[option.key] = value;
  }
  return config;
}

function latestSlot(job) {
  if (!job) return [h("span", { class: "muted" }, "never run on this survey")];
  const pipeline = pipelineOf(job.kind);
  return [
    h(
      "div",
      { class: "latest-head" },
      h("a", { href: `#/jobs/${job.id}` }, `job ${job.id}`),
      statusBadge(job.status),
      job.status === "succeeded" && pipeline
        ? h("a", { href: `#/jobs/${job.id}`, class: "small-link" }, "results & metrics")
        : null,
    ),
    progressBar(job).el,
    h("p", { class: "job-message", title: job.message }, job.message),
  ];
}

function pipelineCard(ctx, survey, form, onStarted) {
  const inputs = {};
  const fields = form.options.map((option) => {
    const { input, el } = optionInput(form.kind, option);
    inputs[option.key] = input;
    return el;
  });
  const slot = h("div", { class: "latest", "data-kind": form.kind });
  const start = h("button", { type: "submit", class: "primary", "data-start": form.kind }, `Start ${form.kind}`);
  const el = h(
    "form",
    { class: "card pipeline", "data-pipeline": form.kind },
    h("h3", {}, form.title),
    h("p", { class: "note" }, form.paper),
    h("div", { class: "options" }, fields),
    start,
    slot,
  );
  el.addEventListener("submit", (event) => {
    event.preventDefault();
    ctx.act(start, async () => {
      const job = await api("/jobs", {
        method: "POST",
        json: { kind: form.kind, survey_id: survey.id, config: configOf(form, inputs) },
      });
      ctx.notice(`Queued ${job.kind} as job ${job.id}.`);
      await onStarted(job);
    });
  });
  return {
    el,
    show(job) {
      slot.replaceChildren(...latestSlot(job));
    },
  };
}

// --- review state ---------------------------------------------------------------------------

function niceMax(value) {
  if (!value) return 1;
  const magnitude = 10 ** Math.floor(Math.log10(value));
  for (const step of [1, 2, 2.5, 5, 10]) {
    if (step * magnitude >= value) return step * magnitude;
  }
  return 10 * magnitude;
}

function pillarSection(stats) {
  const names = stats.classes.map((c) => c.replace(/_/g, " "));
  const total = (xs) => xs.reduce((a, b) => a + b, 0);
  const rows = names.map((n, i) => [n, num(stats.human[i]), num(stats.model[i])]);
  rows.push(["total", num(total(stats.human)), num(total(stats.model))]);
  const groups = names.map((n, i) => ({ label: n, values: { human: stats.human[i], model: stats.model[i] } }));
  const max = niceMax(Math.max(...stats.human, ...stats.model));
  const none = total(stats.human) + total(stats.model) === 0;
  return h(
    "div",
    { class: "review-block", id: "pillar-stats" },
    h("h3", {}, "Pillar labels"),
    table(["class", "human", "model pre-labels"], rows, { class: "grid numeric compact" }),
    none
      ? h("p", { class: "note", id: "pillar-stats-none" }, "No pillar labels yet: label pillars in the viewer, or run the phantom pipeline for model pre-labels.")
      : figure(bars(groups, { series: ["human", "model"], title: "pillars per class", max, unit: "pillars" })),
  );
}

function clutterSection(frames) {
  const instances = frames.reduce((a, f) => a + f.instances, 0);
  const pending = frames.reduce((a, f) => a + f.pending, 0);
  const withInstances = frames.filter((f) => f.instances > 0).length;
  const framesPending = frames.filter((f) => f.pending > 0);
  const decided = instances - pending;
  return h(
    "div",
    { class: "review-block", id: "clutter-review" },
    h("h3", {}, "Clutter review"),
    facts([
      ["frames", num(frames.length)],
      ["frames with removed objects", num(withInstances)],
      ["objects to review", num(instances)],
      ["pending decisions", num(pending)],
      ["frames still pending", num(framesPending.length)],
    ]),
    instances
      ? shareBar(decided / instances, `${num(decided)} of ${num(instances)} decided`)
      : note("No removed objects to review: run the clutter pipeline."),
    framesPending.length
      ? note(`next frames to review: ${framesPending.slice(0, 6).map((f) => f.frame_id).join(", ")}`)
      : null,
  );
}

function guardrailSection(models) {
  const count = (status) => models.filter((m) => m.status === status).length;
  return h(
    "div",
    { class: "review-block", id: "guardrail-models" },
    h("h3", {}, "Guardrail models"),
    facts([
      ["approved", num(count("approved"))],
      ["pending", num(count("pending"))],
      ["rejected", num(count("rejected"))],
    ]),
    models.length
      ? table(
          ["#", "kind", "units", "along the road [m]", "status"],
          models.map((m) => [
            String(m.guardrail_index),
            m.kind,
            num(m.unit_count),
            m.station_m ? `${num(m.station_m[0], 1)} – ${num(m.station_m[1], 1)}` : "",
            statusBadge(m.status),
          ]),
          { class: "grid compact" },
        )
      : note("No reconstructed guardrails: run the guardrail pipeline."),
  );
}

async function latestSucceeded(surveyId, kinds) {
  const found = await Promise.all(
    kinds.map((kind) =>
      api(`/jobs?${new URLSearchParams({ survey_id: surveyId, kind, status: "succeeded", limit: 1 })}`),
    ),
  );
  const jobs = found.flat();
  jobs.sort((a, b) => (a.created_at < b.created_at ? 1 : -1));
  return jobs[0] || null;
}

function exportsSection(survey, runs, guardrailModels, humanLabels, readiness) {
  const { removalRun, clutterRun, clutterMapRun, phantomRun } = runs;
  const approved = guardrailModels.some((m) => m.status === "approved");
  const reasons = {
    removal: removalRun ? null : "needs a finished clutter or phantom run",
    combined:
      clutterMapRun && phantomRun ? null : "needs a finished clutter run and a finished phantom run",
    clutter: clutterRun ? null : "needs a finished clutter run",
    guardrails: approved ? null : "needs an approved guardrail model",
    pillars: humanLabels > 0 ? null : "needs human pillar labels (label pillars in the viewer)",
  };
  const items = EXPORTS.map((e) => {
    let reason = e.needs ? reasons[e.needs] : null;
    const written = removalRun?.result?.files || {};
    if (!reason && e.needs === "removal" && !e.maps.some((m) => written[m])) {
      reason = `${removalRun.kind} job ${removalRun.id}, the newest, wrote none (nothing to put in it)`;
    }
    if (!reason && e.needs === "clutter" && !clutterRun.result?.files?.instances) {
      reason = `${clutterRun.kind} job ${clutterRun.id}, the newest, wrote no review units`;
    }
    const href = `/surveys/${survey.id}/exports/${e.file}`;
    // plain links: the login cookie authorises GET requests, so the browser downloads directly
    const link = reason
      ? h("span", { class: "button disabled", title: reason }, e.text)
      : h(
          "a",
          {
            href,
            class: "button",
            "data-export": e.file,
            download: e.open ? null : "",
            target: e.open ? "_blank" : null,
            rel: e.open ? "noopener" : null,
          },
          e.text,
        );
    let from = "";
    if (e.needs === "removal" && removalRun) from = ` of ${removalRun.kind} job ${removalRun.id}, the newest`;
    if (e.needs === "clutter" && clutterRun) from = ` of ${clutterRun.kind} job ${clutterRun.id}, as reviewed`;
    if (e.needs === "combined" && !reason) {
      from = ` of ${clutterMapRun.kind} job ${clutterMapRun.id} and run:phantom job ${phantomRun.id}`;
    }
    return h("li", {}, link, h("span", { class: "muted" }, reason ? ` ${reason}` : from));
  });
  // the links stay usable while review is pending: the line says what an export would miss
  return [readinessLine(readiness), h("ul", { class: "exports", id: "exports" }, items)];
}

// --- the pages ------------------------------------------------------------------------------

export async function surveyView(ctx, root, id) {
  const survey = await api(`/surveys/${id}`);
  const user = ctx.user;
  const cards = {};
  let lastJobs = {};

  const pipelines = h("div", { class: "pipelines" });
  const review = h("div", { class: "review" });
  const exportsBox = h("div");
  root.append(
    pageHead(survey, "overview"),
    section("Survey", surveyFacts(survey), sensorBlock(ctx, survey)),
    section("Pipelines", pipelines),
    section(
      "Viewer",
      note("Opens the 3D viewer in a new tab, logged in as you."),
      h(
        "div",
        { class: "viewer-modes" },
        VIEWER_MODES.map((m) =>
          h(
            "a",
            {
              href: `/viewer?${new URLSearchParams({ survey: survey.id, mode: m.mode })}`,
              target: "_blank",
              rel: "noopener",
              class: "mode",
              "data-mode": m.mode,
            },
            h("strong", {}, m.title),
            h("span", {}, m.text),
          ),
        ),
      ),
    ),
    section("Review state", review),
  );
  const areas = workAreasBlock(ctx, survey, { onChange: () => loadReview() });
  root.append(section("Work areas", areas.el));
  if (hasRole(user, "reviewer")) root.append(section("Exports", exportsBox));

  async function loadReview() {
    const [stats, frames, models, removalRun, clutterRun, clutterMapRun, phantomRun, readiness] =
      await Promise.all([
        api(`/surveys/${survey.id}/pillars/stats`),
        api(`/surveys/${survey.id}/clutter/frames`),
        api(`/surveys/${survey.id}/guardrails/models`),
        latestSucceeded(survey.id, REMOVAL_KINDS),
        latestSucceeded(survey.id, ["run:clutter"]), // the run whose review units are labelled
        latestSucceeded(survey.id, CLUTTER_KINDS), // the clutter maps a combined export uses
        latestSucceeded(survey.id, ["run:phantom"]),
        api(`/surveys/${survey.id}/export-readiness`),
      ]);
    const runs = { removalRun, clutterRun, clutterMapRun, phantomRun };
    review.replaceChildren(pillarSection(stats), clutterSection(frames), guardrailSection(models));
    const humanLabels = stats.human.reduce((a, b) => a + b, 0);
    exportsBox.replaceChildren(...exportsSection(survey, runs, models, humanLabels, readiness).filter(Boolean));
  }

  async function refresh() {
    const detail = await api(`/surveys/${survey.id}`);
    const jobs = detail.latest_jobs || {};
    let finishedSince = false;
    for (const form of PIPELINE_FORMS) {
      const job = jobs[form.kind];
      const before = lastJobs[form.kind];
      if (JSON.stringify(job) !== JSON.stringify(before)) cards[form.kind].show(job);
      if (before && ACTIVE.has(before.status) && (!job || !ACTIVE.has(job.status))) finishedSince = true;
    }
    if (jobs["clutter:recompute"]?.status !== lastJobs["clutter:recompute"]?.status) finishedSince = true;
    lastJobs = jobs;
    if (finishedSince) await loadReview();
    return Object.values(jobs).some((j) => ACTIVE.has(j.status)) ? 1000 : 5000;
  }

  let poller = null;
  for (const form of PIPELINE_FORMS) {
    cards[form.kind] = pipelineCard(ctx, survey, form, async () => poller?.now());
    pipelines.append(cards[form.kind].el);
  }
  for (const form of PIPELINE_FORMS) cards[form.kind].show(survey.latest_jobs?.[form.kind]);
  lastJobs = survey.latest_jobs || {};
  await loadReview();
  areas.load().catch((error) => ctx.error(error)); // the first read may build the survey's map
  poller = ctx.poll(refresh);
}

export async function surveyMetricsView(ctx, root, id) {
  const survey = await api(`/surveys/${id}`);
  root.append(pageHead(survey, "metrics"));
  const runs = [
    { pipeline: "phantom", title: "Phantom removal (Nagy & Benedek)", kinds: ["run:phantom"] },
    { pipeline: "clutter", title: "Clutter removal (Lee et al.)", kinds: CLUTTER_KINDS },
    { pipeline: "guardrail", title: "Guardrail extraction (Matsumoto et al.)", kinds: ["run:guardrail"] },
  ];
  const jobs = await Promise.all(runs.map((r) => latestSucceeded(survey.id, r.kinds)));
  if (!survey.has_reference_labels) {
    root.append(note("This survey has no reference labels, so runs on it carry no metrics."));
  }
  runs.forEach((run, i) => {
    const job = jobs[i];
    const body = job
      ? [
          note(`newest finished run: job ${job.id} (${job.kind}), finished ${when(job.finished_at)}, ${duration(job.seconds)}`),
          renderMetrics(run.pipeline, job.result?.metrics),
        ]
      : [note("No finished run of this pipeline on this survey yet.")];
    root.append(h("section", { class: "card", "data-metrics": run.pipeline }, h("h2", {}, run.title), body));
  });
}
