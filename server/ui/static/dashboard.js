// The dashboard's scripts: live job progress (server-sent events), and the forms that change
// state, sent to the REST API under /ui/api/v1 with the session cookie and the page's CSRF
// token. No framework and no build step; each page's part runs only when its element is there.
"use strict";

(() => {
  const csrf = document.querySelector('meta[name="csrf-token"]')?.content || "";
  const byId = (id) => document.getElementById(id);

  function flash(message, kind = "error") {
    const box = byId("flash");
    if (!box) return;
    box.textContent = message;
    box.className = `flash ${kind}`;
    box.hidden = !message;
  }

  function signIn() {
    location.href = `/ui/login?next=${encodeURIComponent(location.pathname + location.search)}`;
  }

  // A request to the service; errors become exceptions carrying the API's own message.
  async function api(method, path, { json, form } = {}) {
    const headers = { Accept: "application/json", "X-CSRF-Token": csrf };
    let body;
    if (json !== undefined) {
      headers["Content-Type"] = "application/json";
      body = JSON.stringify(json);
    } else if (form !== undefined) {
      body = form;
    }
    const response = await fetch(path, { method, headers, body, credentials: "same-origin" });
    if (response.status === 401) {
      signIn();
      throw new Error("not signed in");
    }
    const type = response.headers.get("content-type") || "";
    const data = type.includes("application/json") ? await response.json() : null;
    if (!response.ok) {
      const error = data && data.error;
      const err = new Error(error ? error.message : `HTTP ${response.status}`);
      err.status = response.status;
      throw err;
    }
    return data;
  }

  const percent = (fraction) => `${Math.round(100 * (fraction || 0))}%`;

  // A failed job's error as the pages draw it (templates/_macros.html error_text): one line
  // cut where its column ends, the whole text once opened.
  function errorText(text) {
    const box = document.createElement("details");
    box.className = "error-text";
    const summary = document.createElement("summary");
    summary.title = "show the whole error";
    summary.textContent = text;
    box.append(summary);
    return box;
  }

  // One line of a job's log (templates/_macros.html log_line): a line of several lines (a
  // traceback) folded to its first.
  function logEntry(line) {
    const head = `${line.time.slice(11, 19)} ${line.level} `;
    const parts = line.message.split("\n");
    if (parts.length === 1) {
      const div = document.createElement("div");
      div.className = "log-entry";
      div.textContent = head + line.message;
      return div;
    }
    const box = document.createElement("details");
    box.className = "log-entry";
    const summary = document.createElement("summary");
    const more = document.createElement("span");
    more.className = "muted";
    more.textContent = `(${parts.length - 1} more lines)`;
    summary.append(`${head}${parts[0]} `, more);
    box.append(summary, parts.slice(1).join("\n"));
    return box;
  }
  const pngData = (b64) => `data:image/png;base64,${b64}`;

  function busy(button, on) {
    if (!button) return;
    button.disabled = on;
    button.classList.toggle("busy", on);
  }

  // -- one job: progress stream, log tail, cancel, retry ---------------------------------

  function jobPage(section) {
    const id = section.dataset.jobId;
    const terminal = new Set(section.dataset.terminal.split(","));
    let logTimer = null;

    function show(job) {
      section.dataset.status = job.status;
      const status = byId("job-status");
      status.textContent = job.status;
      status.className = `status ${job.status}`;
      byId("job-progress").value = job.progress;
      byId("job-percent").textContent = percent(job.progress);
      byId("job-message").textContent = job.message;
      const error = byId("job-error");
      error.querySelector("summary").textContent = job.error || "";
      error.hidden = !job.error || job.status === "succeeded";
      byId("job-cancel").hidden = terminal.has(job.status);
      byId("job-retry").hidden = !(job.status === "failed" || job.status === "cancelled");
      byId("job-attempts").textContent = job.attempts;
      byId("job-worker").textContent = job.worker_id || "–";
      if (job.result) {
        byId("job-result").textContent = JSON.stringify(job.result, null, 2);
        const link = byId("job-result-link");
        if (job.result.model_id) link.href = `/ui/models#model-${job.result.model_id}`;
        else if (job.result.nerf_id) link.href = "/ui/memory";
        else if (job.kind === "evaluate") link.href = "/ui/models";
        link.hidden = job.status !== "succeeded";
      }
    }

    async function refreshLog() {
      try {
        const data = await api("GET", `/ui/api/v1/jobs/${id}/log?tail=200`);
        const log = byId("job-log");
        const open = new Set([...log.querySelectorAll("details[open]")].map((d) => d.dataset.key));
        log.replaceChildren(
          ...data.lines.map((l) => {
            const entry = logEntry(l);
            entry.dataset.key = `${l.time} ${l.message.length}`;
            if (entry.tagName === "DETAILS" && open.has(entry.dataset.key)) entry.open = true;
            return entry;
          }),
        );
        log.scrollTop = log.scrollHeight;
      } catch (e) {
        flash(`log: ${e.message}`);
      }
    }

    function follow() {
      const events = new EventSource(`/ui/api/v1/jobs/${id}/events`);
      events.addEventListener("progress", (ev) => show(JSON.parse(ev.data)));
      events.addEventListener("end", () => {
        events.close();
        clearInterval(logTimer);
        refreshLog();
      });
      events.onerror = () => {
        // The browser reconnects by itself; a closed stream means it was refused (signed out).
        if (events.readyState === EventSource.CLOSED) {
          clearInterval(logTimer);
          flash("Lost the progress stream; reload the page.");
        }
      };
      logTimer = setInterval(refreshLog, 2000);
    }

    if (!terminal.has(section.dataset.status)) follow();

    byId("job-cancel").addEventListener("click", async (ev) => {
      busy(ev.target, true);
      try {
        show(await api("POST", `/ui/api/v1/jobs/${id}/cancel`));
      } catch (e) {
        flash(e.message);
      } finally {
        busy(ev.target, false);
      }
    });
    byId("job-retry").addEventListener("click", async (ev) => {
      busy(ev.target, true);
      try {
        const job = await api("POST", `/ui/api/jobs/${id}/retry`);
        location.href = `/ui/jobs/${job.id}`;
      } catch (e) {
        flash(e.message);
        busy(ev.target, false);
      }
    });
  }

  // -- the job list: polled while something is queued or running ------------------------

  function jobList(table) {
    const active = () => [...table.querySelectorAll("tr[data-job-id]")].some((tr) => ["queued", "running"].includes(tr.dataset.status));
    async function poll() {
      if (!active()) return;
      try {
        const jobs = await api("GET", "/ui/api/v1/jobs?limit=100");
        for (const job of jobs) {
          const row = table.querySelector(`tr[data-job-id="${job.id}"]`);
          if (!row) continue;
          row.dataset.status = job.status;
          const status = row.querySelector('[data-field="status"]');
          status.textContent = job.status;
          status.className = `status ${job.status}`;
          row.querySelector('[data-field="progress"]').value = job.progress;
          row.querySelector('[data-field="percent"]').textContent = percent(job.progress);
          const message = row.querySelector('[data-field="message"]');
          if (job.status === "failed" && job.error) message.replaceChildren(errorText(job.error));
          else message.textContent = job.message;
        }
      } catch (e) {
        flash(e.message);
      }
      setTimeout(poll, 2000);
    }
    setTimeout(poll, 2000);
  }

  // -- models -----------------------------------------------------------------------------

  function modelButtons() {
    for (const button of document.querySelectorAll("[data-set-current]")) {
      button.addEventListener("click", async () => {
        busy(button, true);
        try {
          await api("POST", `/ui/api/v1/models/${button.dataset.setCurrent}/current`);
          location.reload();
        } catch (e) {
          flash(e.message);
          busy(button, false);
        }
      });
    }
  }

  // -- start work -------------------------------------------------------------------------

  function uploadForm(form) {
    form.addEventListener("submit", async (ev) => {
      ev.preventDefault();
      const button = byId("upload-button");
      const result = byId("upload-result");
      const name = form.elements.scene.value.trim();
      busy(button, true);
      flash("");
      result.hidden = false;
      result.textContent = "uploading…";
      try {
        try {
          await api("POST", "/ui/api/v1/scenes", { json: { name, description: form.elements.description.value } });
        } catch (e) {
          if (e.status !== 409) throw e; // 409: the scene exists, add the frames to it
        }
        const data = new FormData();
        data.append("archive", form.elements.archive.files[0]);
        const out = await api("POST", `/ui/api/v1/scenes/${encodeURIComponent(name)}/archive`, { form: data });
        result.textContent = "";
        const link = document.createElement("a");
        link.href = `/ui/scenes/${out.scene_id}`;
        link.textContent = name;
        link.id = "upload-scene-link";
        result.append("Scene ", link, `: ${out.added.length} frames added, ${out.unchanged.length} unchanged, ${out.replaced.length} replaced, ${out.skipped.length} skipped.`);
      } catch (e) {
        result.textContent = "";
        result.hidden = true;
        flash(e.message);
      } finally {
        busy(button, false);
      }
    });
  }

  function jobForm(form) {
    form.addEventListener("submit", async (ev) => {
      ev.preventDefault();
      const button = form.querySelector('button[type="submit"]');
      const params = {};
      for (const el of form.elements) {
        if (!el.name || el.tagName === "BUTTON") continue;
        if (el.type === "checkbox") params[el.name] = el.checked;
        else if (el.value === "") continue; // left empty: the server's default
        else if (el.type === "number" || el.name === "scene") params[el.name] = Number(el.value);
        else params[el.name] = el.value;
      }
      busy(button, true);
      try {
        const job = await api("POST", "/ui/api/v1/jobs", { json: { kind: form.dataset.kind, params } });
        location.href = `/ui/jobs/${job.id}`;
      } catch (e) {
        flash(e.message);
        busy(button, false);
      }
    });
  }

  // -- try it -----------------------------------------------------------------------------

  const UPLOAD_BYTES = 900 * 1024; // larger images are scaled down before they are sent
  const MAX_SIDE = 1280;

  async function smallEnough(file) {
    if (file.size <= UPLOAD_BYTES) return file;
    const bitmap = await createImageBitmap(file);
    const scale = Math.min(1, MAX_SIDE / Math.max(bitmap.width, bitmap.height));
    const canvas = document.createElement("canvas");
    canvas.width = Math.max(1, Math.round(bitmap.width * scale));
    canvas.height = Math.max(1, Math.round(bitmap.height * scale));
    canvas.getContext("2d").drawImage(bitmap, 0, 0, canvas.width, canvas.height);
    return new Promise((resolve) => canvas.toBlob(resolve, "image/jpeg", 0.92));
  }

  function predictForm(form) {
    form.addEventListener("submit", async (ev) => {
      ev.preventDefault();
      const button = byId("predict-button");
      busy(button, true);
      flash("");
      try {
        const data = new FormData();
        const file = form.elements.image.files[0];
        data.append("image", await smallEnough(file), file.name);
        const out = await api("POST", "/ui/api/predict-preview", { form: data });
        byId("predict-overlay").src = pngData(out.overlay);
        byId("predict-labels").src = pngData(out.labels);
        const legend = byId("predict-legend");
        legend.replaceChildren(
          ...out.legend.map((c) => {
            const item = document.createElement("li");
            item.dataset.classId = c.id;
            const swatch = document.createElement("span");
            swatch.className = "swatch";
            swatch.style.background = c.color;
            item.append(swatch, `${c.id} ${c.name} `);
            const share = document.createElement("span");
            share.className = "muted";
            share.textContent = `${(100 * c.share).toFixed(1)}%`;
            item.append(share);
            return item;
          }),
        );
        byId("predict-model").textContent = `model ${out.model} (#${out.model_id}), ${out.width}×${out.height}`;
        byId("predict-result").hidden = false;
      } catch (e) {
        flash(e.message);
      } finally {
        busy(button, false);
      }
    });
  }

  function renderForm(form) {
    form.addEventListener("submit", async (ev) => {
      ev.preventDefault();
      const button = byId("render-button");
      const value = form.elements.view.value;
      const cut = value.indexOf("/");
      const scene = value.slice(0, cut);
      const frame = encodeURIComponent(value.slice(cut + 1));
      busy(button, true);
      flash("");
      try {
        const info = await api("GET", `/ui/api/v1/scenes/${scene}/frames/${frame}`);
        const view = await api("POST", `/ui/api/v1/scenes/${scene}/render`, { json: { pose: info.pose, channels: ["color", "labels_color"] } });
        byId("render-color").src = pngData(view.images.color);
        byId("render-labels").src = pngData(view.images.labels_color);
        byId("render-camera").src = `/ui/api/v1/scenes/${scene}/frames/${frame}/color`;
        byId("render-result").hidden = false;
      } catch (e) {
        flash(e.message);
      } finally {
        busy(button, false);
      }
    });
  }

  // -- pictures that cannot be drawn say so -----------------------------------------------

  function panelErrors() {
    for (const img of document.querySelectorAll("img[data-panel]")) {
      const fail = () => {
        const note = document.createElement("div");
        note.className = "placeholder";
        note.textContent = `could not draw the ${img.alt}`;
        img.replaceWith(note);
      };
      if (img.complete && img.naturalWidth === 0 && img.src) fail(); // failed before this ran
      else img.addEventListener("error", fail);
    }
  }

  document.addEventListener("DOMContentLoaded", () => {
    const job = byId("job");
    if (job) jobPage(job);
    const jobs = document.querySelector("[data-live-jobs]");
    if (jobs) jobList(jobs);
    modelButtons();
    panelErrors();
    const forms = { "upload-form": uploadForm, "fit-form": jobForm, "adapt-form": jobForm, "predict-form": predictForm, "render-form": renderForm };
    for (const [id, setup] of Object.entries(forms)) {
      const form = byId(id);
      if (form) setup(form);
    }
    document.body.dataset.ready = "1";
  });
})();
