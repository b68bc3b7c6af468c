// Log in: username and password for a bearer token (POST /auth/login).

import { api, session } from "../api.js";
import { h } from "../dom.js";

export async function loginView(ctx, root) {
  if (session.user) {
    location.hash = "#/surveys";
    return;
  }
  const error = h("p", { class: "error", id: "login-error", role: "alert", hidden: true });
  const username = h("input", {
    name: "username",
    id: "login-username",
    autocomplete: "username",
    required: true,
  });
  const password = h("input", {
    name: "password",
    id: "login-password",
    type: "password",
    autocomplete: "current-password",
    required: true,
  });
  const submit = h("button", { type: "submit", class: "primary" }, "Log in");
  const form = h(
    "form",
    { class: "login card", id: "login-form" },
    h("h1", {}, "mmsclean"),
    h("p", { class: "note" }, "Cleaning mobile-mapping point clouds: jobs, review and export."),
    h("label", {}, "Username", username),
    h("label", {}, "Password", password),
    error,
    submit,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.hidden = true;
    submit.disabled = true;
    try {
      const answer = await api("/auth/login", {
        method: "POST",
        json: { username: username.value.trim(), password: password.value },
      });
      session.save(answer.access_token, answer.user);
      const back = serverPage(new URLSearchParams(location.search).get("next"));
      if (back) {
        location.assign(back); // the viewer link that sent a logged-out browser here
        return;
      }
      const next = sessionStorage.getItem("mmsclean.next");
      sessionStorage.removeItem("mmsclean.next");
      location.hash = next && next !== "#/login" ? next : "#/surveys";
    } catch (e) {
      error.textContent = e.message; // the API's one-line detail
      error.hidden = false;
      password.select();
    } finally {
      submit.disabled = false;
    }
  });
  root.append(h("div", { class: "login-page" }, form));
  username.focus();
}

/** A `next` page of this server (the viewer sends logged-out browsers to `/?next=/viewer...`);
 * null for anything else, so a crafted link cannot send someone elsewhere after logging in. */
function serverPage(next) {
  if (!next || !next.startsWith("/viewer") || next.includes("\\")) return null;
  const url = new URL(next, location.origin);
  return url.origin === location.origin ? url.pathname + url.search : null;
}
