// Requests to this service's API with the HttpOnly session cookie, and its errors in words.

export const API = "/api/v1";

export class ApiError extends Error {
  constructor(status, code, detail) {
    super(detail || code || `HTTP ${status}`);
    this.status = status;
    this.code = code;
    this.detail = detail;
  }
}

export function describeError(error) {
  if (!(error instanceof ApiError)) return `The service could not be reached (${error.message}). Is it running?`;
  if (error.status === 401) return "Your session has ended: the token was revoked or the session expired. Sign in again.";
  if (error.status === 403) return `Not allowed: ${error.detail || "this token's role cannot do this."}`;
  if (error.status === 404) return `Not found: ${error.detail || "it does not exist or belongs to another organisation."}`;
  if (error.status === 413) return `The file is too large for this service: ${error.detail || ""}`;
  if (error.status === 415) return `Unknown file format: ${error.detail || ""}`;
  return error.detail || error.message;
}

/** The items of a list answer (a bare array or a page with `items`). */
export function itemsOf(payload) {
  if (Array.isArray(payload)) return payload;
  return payload && Array.isArray(payload.items) ? payload.items : [];
}

export async function api(path, { method = "GET", body, headers = {} } = {}) {
  const options = { method, credentials: "same-origin", headers: { Accept: "application/json", ...headers } };
  if (body !== undefined) {
    options.body = JSON.stringify(body);
    options.headers["Content-Type"] = "application/json";
  }
  let response;
  try {
    response = await fetch(path.startsWith("/") ? path : `${API}/${path}`, options);
  } catch (error) {
    throw new Error(error.message || "network error");
  }
  const text = await response.text();
  let payload = null;
  if (text) {
    try {
      payload = JSON.parse(text);
    } catch {
      payload = { detail: text.slice(0, 300) };
    }
  }
  if (!response.ok) {
    let detail = payload && payload.detail;
    if (Array.isArray(detail)) detail = detail.map((item) => item.msg || JSON.stringify(item)).join("; ");
    throw new ApiError(response.status, payload && payload.error, detail);
  }
  return payload;
}

/** Upload `file` as the raw body with progress; resolves with the JSON answer. */
export function uploadScan(siteId, file, reference, onProgress, sensorOrigin = "") {
  return new Promise((resolve, reject) => {
    const query = new URLSearchParams({ reference: String(reference), filename: file.name });
    if (sensorOrigin) query.set("sensor_origin", sensorOrigin);
    const request = new XMLHttpRequest();
    request.open("POST", `${API}/sites/${encodeURIComponent(siteId)}/scans?${query}`);
    request.withCredentials = true;
    request.setRequestHeader("Content-Type", "application/octet-stream");
    request.setRequestHeader("Accept", "application/json");
    request.setRequestHeader("Idempotency-Key", `${siteId}-${file.name}-${file.size}-${file.lastModified}-${reference}-${Date.now()}`);
    request.upload.onprogress = (event) => {
      if (event.lengthComputable) onProgress(event.loaded / event.total);
    };
    request.onload = () => {
      let payload = null;
      try {
        payload = request.responseText ? JSON.parse(request.responseText) : null;
      } catch {
        payload = { detail: request.responseText.slice(0, 300) };
      }
      if (request.status >= 200 && request.status < 300) resolve(payload);
      else reject(new ApiError(request.status, payload && payload.error, payload && payload.detail));
    };
    request.onerror = () => reject(new Error("the upload was interrupted"));
    request.send(file);
  });
}
