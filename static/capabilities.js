// What this server reads and runs (GET /capabilities): upload formats and detectors, fetched
// once per page load, so the file picker and the detector forms never offer what it refuses.

import { api } from "./api.js";

let pending = null;

/** The server's capabilities (cached; a failure is retried on the next call). */
export function loadCapabilities() {
  if (!pending) {
    pending = api("capabilities").catch((failure) => {
      pending = null;
      throw failure;
    });
  }
  return pending;
}
