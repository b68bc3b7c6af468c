// The dashboard shell: hash routes, the top bar, the session, and one context per page view
// that owns the page's timers (so leaving a page stops its polling).

import { ApiError, api, session } from "./api.js";
import { clear, h } from "./dom.js";
import { jobView, jobsView } from "./views/jobs.js";
import { loginView } from "./views/login.js";
import { modelsView } from "./views/models.js";
import { surveyMetricsView, surveyView } from "./views/survey.js";
import { surveysView } from "./views/surveys.js";

const ROUTES = [
  { pattern: /^\/login$/, view: loginView, public: true, nav: null },
  { pattern: /^\/surveys$/, view: surveysView, nav: "surveys" },
  { pattern: /^\/surveys\/(\d+)$/, view: surveyView, nav: "surveys" },
  { pattern: /^\/surveys\/(\d+)\/metrics$/, view: surveyMetricsView, nav: "surveys" },
  { pattern: /^\/jobs$/, view: jobsView, nav: "jobs" },
  { pattern: /^\/jobs\/(\d+)$/, view: jobView, nav: "jobs" },
  { pattern: /^\/models$/, view: modelsView, nav: "models" },
];

const root = document.getElementById("view");
const flashEl = document.getElementById("flash");
let current = null; // the context of the page on screen
let flashTimer = null;

/** A message under the top bar: errors stay until the next page, notices fade. */
export function flash(message, kind = "error") {
  clearTimeout(flashTimer);
  flashEl.textContent = message;
  flashEl.className = `flash ${kind}`;
  flashEl.hidden = false;
  if (kind !== "error") flashTimer = setTimeout(() => (flashEl.hidden = true), 4000);
}

function clearFlash() {
  clearTimeout(flashTimer);
  flashEl.hidden = true;
}

class PageContext {
  constructor(user, query) {
    this.user = user;
    this.query = query;
    this.left = false;
    this.timers = new Set();
  }

  /** Run STEP now and again after the delay (ms) it returns, until the page is left or it
   * returns nothing; a failing step is reported and retried after 5 s. Returns `{now()}`:
   * run it at once (after a click changed something) instead of waiting for the timer. */
  poll(step) {
    let timer = null;
    let running = false;
    let again = false;
    const stopTimer = () => {
      clearTimeout(timer);
      this.timers.delete(timer);
      timer = null;
    };
    const loop = async () => {
      if (this.left) return;
      if (running) {
        again = true; // one run at a time; run once more when this one ends
        return;
      }
      running = true;
      let delay;
      try {
        delay = await step();
      } catch (error) {
        this.error(error);
        delay = error instanceof ApiError && error.status === 401 ? null : 5000;
      }
      running = false;
      if (this.left) return;
      if (again) {
        again = false;
        loop();
      } else if (delay) {
        timer = setTimeout(() => {
          stopTimer();
          loop();
        }, delay);
        this.timers.add(timer);
      }
    };
    loop();
    return {
      now: () => {
        stopTimer();
        loop();
      },
    };
  }

  error(error) {
    if (this.left) return;
    if (error instanceof ApiError && error.status === 401) return; // handled by the login redirect
    flash(error instanceof Error ? error.message : String(error), "error");
    if (!(error instanceof ApiError)) console.error(error);
  }

  notice(message) {
    if (!this.left) flash(message, "notice");
  }

  /** Run an action (button click) once at a time: the button is disabled while it runs and
   * errors are shown as the API's one-line detail. */
  async act(button, action) {
    if (button) button.disabled = true;
    try {
      return await action();
    } catch (error) {
      this.error(error);
      return undefined;
    } finally {
      if (button) button.disabled = false;
    }
  }

  leave() {
    this.left = true;
    for (const timer of this.timers) clearTimeout(timer);
    this.timers.clear();
  }
}

export function navigate(hash) {
  if (location.hash === hash) route();
  else location.hash = hash;
}

function showTopbar(user) {
  const bar = document.getElementById("topbar");
  bar.hidden = !user;
  if (!user) return;
  document.getElementById("who-name").textContent = user.username;
  const role = document.getElementById("who-role");
  role.textContent = user.role;
  role.className = `badge role role-${user.role}`;
}

function markNav(nav) {
  for (const link of document.querySelectorAll("[data-nav]")) {
    link.classList.toggle("active", link.dataset.nav === nav);
  }
}

async function route() {
  const [path, query = ""] = (location.hash.replace(/^#/, "") || "/surveys").split("?");
  const found = ROUTES.map((r) => ({ r, m: path.match(r.pattern) })).find((x) => x.m);
  const user = session.user;
  if (current) current.leave();
  clearFlash();
  if (!found) {
    navigate("#/surveys");
    return;
  }
  if (!found.r.public && !user) {
    sessionStorage.setItem("mmsclean.next", location.hash);
    navigate("#/login");
    return;
  }
  showTopbar(found.r.public ? null : user);
  markNav(found.r.nav);
  const context = new PageContext(user, new URLSearchParams(query));
  current = context;
  clear(root);
  root.dataset.page = found.r.nav || "login";
  try {
    await found.r.view(context, root, ...found.m.slice(1));
  } catch (error) {
    if (context === current) {
      context.error(error);
      if (!(error instanceof ApiError && error.status === 401)) {
        root.append(h("p", { class: "note" }, "This page could not be loaded."));
      }
    }
  }
}

async function logout() {
  try {
    await api("/auth/logout", { method: "POST" }); // clears the HttpOnly cookie
  } catch {
    // an expired token cannot log out; forgetting it is enough
  }
  session.clear();
  navigate("#/login");
}

window.addEventListener("mmsclean:unauthorized", () => {
  if (!session.token) return;
  session.clear();
  sessionStorage.setItem("mmsclean.next", location.hash);
  navigate("#/login");
  flash("Your session has ended; please log in again.", "error");
});
window.addEventListener("hashchange", route);
document.getElementById("logout").addEventListener("click", logout);

async function start() {
  if (session.token) {
    try {
      session.setUser(await api("/auth/me")); // the role may have changed since login
    } catch (error) {
      if (error.status === 401) session.clear(); // a server that is down ends no session
    }
  }
  route();
}

start();
