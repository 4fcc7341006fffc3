// Detector fields (method, variant, parameters as JSON) for the site and re-run forms.

import { h } from "./dom.js";

const PARAMS_HINT = 'Keyword parameters as JSON, e.g. {"false_alarm_rate": 0.01, "max_points": 4000, '
  + '"localisation": {"min_region_points": 200}}. Empty: the detector\'s defaults.';

/**
 * Method and variant selects and a parameters box, prefilled with `detector`; `prefix` names
 * the ids (`${prefix}-method`...). `read()` gives {method, variant, params} or throws an Error
 * that says what to fix.
 */
export function detectorFields(capabilities, detector, prefix) {
  const chosen = detector || capabilities.default_detector;
  const methodSelect = h("select", { id: `${prefix}-method`, name: "method" },
    capabilities.detector_methods.map((method) => h("option", { value: method, selected: method === chosen.method }, method)));
  const variantSelect = h("select", { id: `${prefix}-variant`, name: "variant" },
    capabilities.detector_variants.map((variant) => h("option", { value: variant, selected: variant === chosen.variant }, variant)));
  const paramsText = chosen.params && Object.keys(chosen.params).length ? JSON.stringify(chosen.params) : "";
  const paramsInput = h("textarea", {
    id: `${prefix}-params`, name: "params", rows: 2, cols: 48, placeholder: "{} (defaults)", title: PARAMS_HINT,
  }, paramsText);
  const element = h("fieldset", { class: "detector-fields", id: `${prefix}-detector` },
    h("legend", {}, "Detector"),
    h("label", { for: `${prefix}-method` }, "Method"), methodSelect,
    h("label", { for: `${prefix}-variant` }, "Variant"), variantSelect,
    h("label", { for: `${prefix}-params` }, "Parameters"), paramsInput,
    h("p", { class: "muted detector-hint" }, PARAMS_HINT));

  function read() {
    const text = paramsInput.value.trim();
    let params = {};
    if (text) {
      try {
        params = JSON.parse(text);
      } catch (error) {
        throw new Error(`the parameters are not valid JSON (${error.message}); write an object like {"max_points": 4000} or leave them empty`);
      }
      if (params === null || typeof params !== "object" || Array.isArray(params)) {
        throw new Error('the parameters must be a JSON object like {"max_points": 4000}');
      }
    }
    return { method: methodSelect.value, variant: variantSelect.value, params };
  }
  return { element, read };
}
