// Talking to the mmsclean API. The token lives in sessionStorage and goes out as a bearer header
// on every call: the server accepts its login cookie for reads only, so writes need the header.

const KEY = "mmsclean.session";
const ROLE_RANK = { annotator: 1, reviewer: 2, admin: 3 };

export const session = {
  read() {
    try {
      return JSON.parse(sessionStorage.getItem(KEY)) || null;
    } catch {
      return null;
    }
  },
  get token() {
    return this.read()?.token ?? null;
  },
  get user() {
    return this.read()?.user ?? null;
  },
  save(token, user) {
    sessionStorage.setItem(KEY, JSON.stringify({ token, user }));
  },
  setUser(user) {
    const current = this.read();
    if (current) this.save(current.token, user);
  },
  clear() {
    sessionStorage.removeItem(KEY);
  },
};

/** Roles nest: an admin may do what a reviewer may, a reviewer what an annotator may. */
export function hasRole(user, role) {
  return (ROLE_RANK[user?.role] ?? 0) >= ROLE_RANK[role];
}

export class ApiError extends Error {
  constructor(status, detail, body = null) {
    super(detail);
    this.status = status;
    this.body = body;
  }
}

/** The API's one-line `detail` (validation errors: their messages joined). */
function detailOf(status, statusText, text) {
  let body = null;
  try {
    body = JSON.parse(text);
  } catch {
    return text.trim().split("\n")[0] || `${status} ${statusText}`;
  }
  const detail = body?.detail;
  if (typeof detail === "string") return { detail, body };
  if (Array.isArray(detail)) {
    return { detail: detail.map((d) => d.msg ?? JSON.stringify(d)).join("; "), body };
  }
  return { detail: `${status} ${statusText}`, body };
}

function failure(status, statusText, text) {
  const parsed = detailOf(status, statusText, text);
  if (typeof parsed === "string") return new ApiError(status, parsed);
  return new ApiError(status, parsed.detail, parsed.body);
}

function unauthorized(path) {
  // a failed login is the form's business; any other 401 means the session is over
  if (path !== "/auth/login") window.dispatchEvent(new CustomEvent("mmsclean:unauthorized"));
}

/** fetch PATH with the bearer token; JSON in (`json`) and out; throws ApiError with the detail. */
export async function api(path, { method = "GET", json, headers = {} } = {}) {
  const init = { method, headers: { Accept: "application/json", ...headers } };
  const token = session.token;
  if (token) init.headers.Authorization = `Bearer ${token}`;
  if (json !== undefined) {
    init.body = JSON.stringify(json);
    init.headers["Content-Type"] = "application/json";
  }
  let response;
  try {
    response = await fetch(path, init);
  } catch {
    throw new ApiError(0, "the server cannot be reached");
  }
  if (response.status === 401) unauthorized(path);
  if (!response.ok) {
    throw failure(response.status, response.statusText, await response.text());
  }
  if (response.status === 204) return null;
  const type = response.headers.get("content-type") || "";
  return type.includes("json") ? response.json() : response.text();
}

let vocabularyRead = null;

/** The label vocabulary (`GET /vocabulary`: the pillar classes in label order), read once per
 * page; after a failed read the next caller asks again. */
export function vocabulary() {
  vocabularyRead ??= api("/vocabulary").catch((err) => {
    vocabularyRead = null;
    throw err;
  });
  return vocabularyRead;
}

/** POST FILE as the raw body to PATH, reporting upload progress (fetch has no upload progress
 * events, XMLHttpRequest does). Resolves with the JSON answer. */
export function uploadRaw(path, file, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", path);
    xhr.setRequestHeader("Content-Type", "application/octet-stream");
    xhr.setRequestHeader("Accept", "application/json");
    const token = session.token;
    if (token) xhr.setRequestHeader("Authorization", `Bearer ${token}`);
    xhr.upload.onprogress = (event) => {
      if (event.lengthComputable) onProgress(event.loaded, event.total);
    };
    xhr.upload.onload = () => onProgress(file.size, file.size, true);
    xhr.onerror = () => reject(new ApiError(0, "the upload was interrupted"));
    xhr.onload = () => {
      if (xhr.status === 401) unauthorized(path);
      if (xhr.status >= 200 && xhr.status < 300) {
        try {
          resolve(JSON.parse(xhr.responseText));
        } catch {
          resolve(null);
        }
      } else {
        reject(failure(xhr.status, xhr.statusText, xhr.responseText));
      }
    };
    xhr.send(file);
  });
}
