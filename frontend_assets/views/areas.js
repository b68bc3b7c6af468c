// The review workflow on a survey's page (as CVAT jobs do it): the survey's drive cut into work
// areas, each assigned to an annotator (and optionally a reviewer), marked labelled by its
// assignee, signed off or rejected with a comment by a reviewer; each with its coverage. And
// the export readiness line shown beside the export links (the exports stay usable).

import { api, hasRole } from "../api.js";
import { h, note, num, statusBadge } from "../dom.js";

/** "Warning: ..." above the export links while review is pending; nothing when ready. */
export function readinessLine(readiness) {
  if (!readiness?.warning) return null;
  return h("p", { class: "export-warning", id: "export-warning", role: "status" }, `Warning: ${readiness.warning}`);
}

function metres(a) {
  return `${num(a.station_start, 0)} – ${num(a.station_end, 0)} m`;
}

function nameOf(users, id, none) {
  if (id === null || id === undefined) return h("span", { class: "muted" }, none);
  const u = users.find((x) => x.id === id);
  return u ? u.username : `user ${id}`;
}

function coverageCell(c) {
  const share = c.pillars ? `${(100 * c.labelled_fraction).toFixed(1)} %` : "–";
  return h(
    "span",
    { "data-labelled": String(c.human_labelled) },
    h("strong", {}, share),
    h("span", { class: "muted" }, ` ${num(c.human_labelled)} of ${num(c.pillars)} pillars`),
  );
}

function pendingCell(c) {
  const parts = [];
  if (c.clutter_pending) parts.push(`${num(c.clutter_pending)} clutter`);
  if (c.model_unreviewed) parts.push(`${num(c.model_unreviewed)} pre-labels`);
  if (c.slices_unreviewed) parts.push(`${num(c.slices_unreviewed)} slices`);
  if (c.models_pending) parts.push(`${num(c.models_pending)} guardrail models`);
  const total = c.clutter_pending + c.model_unreviewed + c.slices_unreviewed + c.models_pending;
  return h("span", { "data-pending": String(total) }, parts.length ? parts.join(", ") : h("span", { class: "muted" }, "none"));
}

function userOptions(users, selected, noneText) {
  return [
    h("option", { value: "", selected: selected === null }, noneText),
    ...users.map((u) => h("option", { value: String(u.id), selected: u.id === selected }, `${u.username} (${u.role})`)),
  ];
}

export function workAreasBlock(ctx, survey, { onChange } = {}) {
  const user = ctx.user;
  const isReviewer = hasRole(user, "reviewer");
  const el = h("div", { id: "work-areas" });
  let users = [];

  async function post(path, body, button, done) {
    await ctx.act(button, async () => {
      const area = await api(`/surveys/${survey.id}/areas${path}`, { method: "POST", json: body });
      ctx.notice(done(area));
      await load();
      if (onChange) await onChange();
    });
  }

  function createForm(areas) {
    const length = h("input", { id: "areas-length", type: "number", min: 5, max: 10000, step: 5, value: "100" });
    const replace = h("input", { type: "checkbox", id: "areas-replace" });
    const button = h("button", { type: "submit", class: "primary", id: "areas-create" }, areas.length ? "Cut again" : "Create work areas");
    const form = h(
      "form",
      { id: "areas-form", class: "inline-form" },
      h("label", {}, "Length along the drive [m]", length),
      areas.length ? h("label", { class: "check" }, replace, "replace the existing areas (their assignments and sign-offs go)") : null,
      button,
    );
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      post("", { length_m: Number(length.value), replace: replace.checked }, button, (rows) => `Cut ${rows.length} work areas.`);
    });
    return form;
  }

  function actions(a) {
    const cells = [];
    const ver = { version: a.version };
    if (isReviewer && a.state !== "signed_off") {
      const annotators = users.filter((u) => u.is_active);
      const reviewers = annotators.filter((u) => hasRole(u, "reviewer"));
      const assignee = h("select", { "data-assignee": String(a.area_index), "aria-label": "assignee" }, userOptions(annotators, a.assignee_id, "nobody"));
      const reviewer = h("select", { "data-reviewer": String(a.area_index), "aria-label": "reviewer" }, userOptions(reviewers, a.reviewer_id, "any reviewer"));
      const button = h("button", { type: "button", "data-action": "assign" }, "Assign");
      button.addEventListener("click", () => {
        const id = (s) => (s.value ? Number(s.value) : null);
        post(`/${a.id}/assign`, { ...ver, assignee_id: id(assignee), reviewer_id: id(reviewer) }, button, () => `Work area ${a.area_index} assigned.`);
      });
      cells.push(h("span", { class: "area-assign" }, assignee, reviewer, button));
    }
    if (a.state === "open" && a.assignee_id === user.id) {
      const button = h("button", { type: "button", class: "primary", "data-action": "labelled" }, "Mark labelled");
      button.addEventListener("click", () => post(`/${a.id}/labelled`, ver, button, () => `Work area ${a.area_index} marked labelled.`));
      cells.push(button);
    }
    const mayReview = isReviewer && (a.reviewer_id === null || a.reviewer_id === user.id || hasRole(user, "admin"));
    if (mayReview && a.state === "labelled") {
      const button = h("button", { type: "button", class: "primary", "data-action": "sign-off" }, "Sign off");
      button.addEventListener("click", () => post(`/${a.id}/sign-off`, ver, button, () => `Work area ${a.area_index} signed off.`));
      cells.push(button);
    }
    if (mayReview && (a.state === "labelled" || a.state === "signed_off")) {
      const comment = h("input", { type: "text", maxlength: 1000, placeholder: "what is wrong", "data-comment": String(a.area_index), "aria-label": "rejection comment" });
      const button = h("button", { type: "button", "data-action": "reject" }, a.state === "signed_off" ? "Reopen" : "Reject");
      button.addEventListener("click", () => {
        if (!comment.value.trim()) {
          ctx.error(new Error("comment: say what is wrong: a rejection needs a comment"));
          return;
        }
        post(`/${a.id}/reject`, { ...ver, comment: comment.value }, button, () => `Work area ${a.area_index} sent back to its annotator.`);
      });
      cells.push(h("span", { class: "area-reject" }, comment, button));
    }
    return h("div", { class: "area-actions" }, cells);
  }

  function row(a) {
    // the viewer opens looking down at the area (its pillars' box), in the labelling mode
    const viewer = h(
      "a",
      { href: `/viewer?${new URLSearchParams({ survey: survey.id, mode: "pillars", area: a.id })}`, target: "_blank", rel: "noopener", "data-viewer-area": String(a.area_index), title: `Open the viewer at ${num(a.station_start, 0)}-${num(a.station_end, 0)} m along the drive` },
      "viewer",
    );
    const state = [statusBadge(a.state)];
    if (a.state === "open" && a.comment) state.push(h("div", { class: "area-comment", "data-rejected": String(a.area_index) }, `rejected: ${a.comment}`));
    return h(
      "tr",
      { "data-area": String(a.area_index), "data-state": a.state },
      h("td", {}, String(a.area_index)),
      h("td", {}, metres(a), " ", viewer),
      h("td", { "data-col": "assignee" }, nameOf(users, a.assignee_id, "nobody")),
      h("td", { "data-col": "reviewer" }, nameOf(users, a.reviewer_id, "any reviewer")),
      h("td", {}, state),
      h("td", {}, coverageCell(a.coverage)),
      h("td", {}, pendingCell(a.coverage)),
      h("td", {}, actions(a)),
    );
  }

  async function load() {
    const [areas, all] = await Promise.all([api(`/surveys/${survey.id}/areas`), api("/users")]);
    users = all;
    const signed = areas.filter((a) => a.state === "signed_off").length;
    const parts = [
      note(
        areas.length
          ? `${areas.length} areas along the drive, ${signed} signed off. The viewer link opens the survey looking down at the area.`
          : "No work areas yet: cut the survey's drive into areas to assign them.",
      ),
    ];
    if (isReviewer) parts.push(createForm(areas));
    if (areas.length) {
      parts.push(
        h(
          "table",
          { class: "grid compact", id: "areas-table" },
          h(
            "thead",
            {},
            h("tr", {}, ["#", "along the drive", "assignee", "reviewer", "state", "labelled", "pending", ""].map((x) => h("th", {}, x))),
          ),
          h("tbody", {}, areas.map(row)),
        ),
      );
    }
    el.replaceChildren(...parts);
  }

  return { el, load };
}
