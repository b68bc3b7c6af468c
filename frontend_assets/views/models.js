// Trained model versions with their held-out metrics; promote (admin), retrain on demand
// (admin), and the state of the new-labels retraining trigger.

import { api, hasRole } from "../api.js";
import { ACTIVE, facts, h, note, num, pct, progressBar, section, shareBar, statusBadge, when } from "../dom.js";
import { modelDetails, modelHeadline } from "../metrics.js";
import { sensorBadge } from "../sensors.js";

const TRAINABLE = [
  { pipeline: "phantom", text: "phantom CNN from the human pillar labels" },
  { pipeline: "guardrail", text: "guardrail slice classifier from the reviewed slices" },
];

function trainedOn(model) {
  const t = model.trained_on || {};
  if (t.shipped) return "shipped with mmsclean";
  const parts = [];
  if (t.human_labels !== undefined) parts.push(`${num(t.human_labels)} human pillar labels`);
  if (t.reviewed_slices !== undefined) parts.push(`${num(t.reviewed_slices)} reviewed slices`);
  if (Array.isArray(t.surveys) && t.surveys.length) parts.push(`surveys ${t.surveys.join(", ")}`);
  return parts.join("; ");
}

function modelRow(ctx, model, refresh) {
  const score = modelHeadline(model);
  const promote =
    hasRole(ctx.user, "admin") && !model.is_promoted
      ? h(
          "button",
          {
            type: "button",
            class: "small",
            "data-action": "promote",
            "data-model": model.id,
            onclick: (event) =>
              ctx.act(event.currentTarget, async () => {
                await api(`/models/${model.id}/promote`, { method: "POST" });
                ctx.notice(`Promoted ${model.name}: new ${model.pipeline} runs use it.`);
                await refresh();
              }),
          },
          "Promote",
        )
      : null;
  // validation plots in a full-width row under the version, drawn when first opened
  const detailCell = h("td", { colspan: "11" });
  const detailRow = h("tr", { class: "model-detail", hidden: true }, detailCell);
  const toggle = h(
    "button",
    {
      type: "button",
      class: "link small",
      "data-action": "metrics",
      onclick: () => {
        if (!detailCell.children.length) detailCell.append(modelDetails(model));
        detailRow.hidden = !detailRow.hidden;
        toggle.textContent = detailRow.hidden ? "metrics" : "hide metrics";
      },
    },
    "metrics",
  );
  const delta =
    score.baseline !== null && score.baseline !== undefined && score.f1 !== null
      ? `${score.f1 - score.baseline >= 0 ? "+" : ""}${(score.f1 - score.baseline).toFixed(1)} vs. base`
      : "";
  const row = h(
    "tr",
    { "data-model": model.id },
    h("td", {}, String(model.id)),
    h("td", {}, model.pipeline),
    h("td", { class: "sensor-cell" }, sensorBadge(model.sensor_kind, `trained for ${model.sensor_kind} scanners`)),
    h("td", {}, h("span", { class: "model-name" }, model.name), " ", toggle),
    h("td", {}, model.is_promoted ? h("span", { class: "badge promoted" }, "promoted") : ""),
    h(
      "td",
      { class: "num" },
      score.f1 === null ? "n/a" : pct(score.f1),
      score.detail ? h("span", { class: "muted" }, ` (${score.detail})`) : null,
      delta ? h("div", { class: "muted" }, delta) : null,
    ),
    h("td", { class: "num" }, score.accuracy === null ? "" : pct(score.accuracy)),
    h("td", {}, trainedOn(model)),
    h("td", {}, when(model.created_at)),
    h("td", {}, model.job_id ? h("a", { href: `#/jobs/${model.job_id}` }, `job ${model.job_id}`) : ""),
    h("td", { class: "actions" }, promote),
  );
  return [row, detailRow];
}

function retrainingPanel(ctx, state, jobs, refresh) {
  const parts = [];
  const auto = state.threshold > 0;
  parts.push(
    facts([
      ["automatic retraining", auto ? `every ${num(state.threshold)} new human pillar labels` : "off"],
      ["new human labels since the last training that succeeded", num(state.new_labels)],
      [
        "training job waiting or running",
        state.pending_job_id ? h("a", { href: `#/jobs/${state.pending_job_id}` }, `job ${state.pending_job_id}`) : "none",
      ],
    ]),
  );
  if (auto) {
    parts.push(
      shareBar(
        Math.min(1, state.new_labels / state.threshold),
        `${num(state.new_labels)} of ${num(state.threshold)} labels to the next automatic run`,
      ),
    );
  }
  const running = jobs.filter((j) => ACTIVE.has(j.status));
  for (const job of running) {
    parts.push(
      h(
        "div",
        { class: "training-job" },
        h("a", { href: `#/jobs/${job.id}` }, `job ${job.id} ${job.kind}`),
        statusBadge(job.status),
        progressBar(job).el,
        h("span", { class: "job-message" }, job.message),
      ),
    );
  }
  if (hasRole(ctx.user, "admin")) {
    const readiness = Object.fromEntries((state.pipelines || []).map((p) => [p.pipeline, p]));
    parts.push(
      h(
        "div",
        { class: "retrain-buttons" },
        TRAINABLE.map((t) => retrainRow(ctx, t, readiness[t.pipeline], refresh)),
      ),
      note("A new version is promoted only when it scores at least as well as the current one on held-out labels."),
    );
  } else {
    parts.push(note("Retraining and promotion are for admins."));
  }
  return parts;
}

/** A retrain button with what it needs: disabled, with the reason, until the labels can train
 * the model; the last training's failure shown where it was started. */
function retrainRow(ctx, t, ready, refresh) {
  const blocked = ready?.blocked_by ?? null;
  const button = h(
    "button",
    {
      type: "button",
      class: "primary",
      "data-retrain": t.pipeline,
      disabled: blocked !== null,
      title: `fine-tune the ${t.text}; promoted only if not worse on held-out labels`,
      onclick: (event) =>
        ctx.act(event.currentTarget, async () => {
          const job = await api("/models/retrain", { method: "POST", json: { pipeline: t.pipeline } });
          ctx.notice(`Queued ${job.kind} as job ${job.job_id}.`);
          await refresh();
        }),
    },
    `Retrain ${t.pipeline}`,
  );
  const needs = h(
    "span",
    { class: blocked ? "muted" : "", "data-needs": t.pipeline },
    blocked ? `Not yet: ${blocked}.` : "Ready: the labels can train it.",
  );
  const lines = [needs];
  if (ready?.last_job_status === "failed") {
    lines.push(
      h(
        "span",
        { class: "error-text", "data-failed": t.pipeline },
        "The last retraining failed (",
        h("a", { href: `#/jobs/${ready.last_job_id}` }, `job ${ready.last_job_id}`),
        `): ${ready.last_job_message || "no reason given"}`,
      ),
    );
  }
  return h("div", { class: "retrain-row" }, button, h("div", { class: "retrain-needs" }, lines));
}

function modelsTable(ctx, models, refresh) {
  if (!models.length) {
    return note("No model versions yet: they appear once a pipeline has run or a training finished.");
  }
  const head = ["ID", "Pipeline", "Sensor", "Version", "", "F [%]", "Accuracy [%]", "Trained on", "Created", "Job", ""];
  return h(
    "table",
    { class: "grid", id: "models" },
    h("thead", {}, h("tr", {}, head.map((x) => h("th", {}, x)))),
    h("tbody", {}, models.map((m) => modelRow(ctx, m, refresh))),
  );
}

export async function modelsView(ctx, root) {
  const panel = h("div", { id: "retraining" });
  const tableBox = h("div", { id: "models-table" });
  root.append(
    h("div", { class: "page-head" }, h("h1", {}, "Models")),
    section("Retraining", panel),
    section("Versions", note("F and accuracy on labels held out of training, in %."), tableBox),
  );
  // panel and table redraw separately, so a moving training bar keeps open details open
  let shownPanel = "";
  let shownModels = "";
  let poller = null;
  const changed = async () => poller?.now();
  async function refresh() {
    const [models, state, phantomJobs, guardrailJobs] = await Promise.all([
      api("/models"),
      api("/models/retraining"),
      api("/jobs?kind=train:phantom&limit=5"),
      api("/jobs?kind=train:guardrail&limit=5"),
    ]);
    const jobs = [...phantomJobs, ...guardrailJobs];
    const panelSignature = JSON.stringify([state, jobs]);
    if (panelSignature !== shownPanel) {
      shownPanel = panelSignature;
      panel.replaceChildren(...retrainingPanel(ctx, state, jobs, changed));
    }
    const modelsSignature = JSON.stringify(models);
    if (modelsSignature !== shownModels) {
      shownModels = modelsSignature;
      tableBox.replaceChildren(modelsTable(ctx, models, changed));
    }
    return jobs.some((j) => ACTIVE.has(j.status)) ? 1000 : 5000;
  }
  poller = ctx.poll(refresh);
}
