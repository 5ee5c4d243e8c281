// cblrs login page: posts the user's name and password (or the run's login link token) as
// JSON to /api/login, which sets the session cookie and answers the session's page token;
// the page token goes to this origin's sessionStorage (common.js sends it on every request),
// then the browser goes where the user was going (a path of this site only).
"use strict";

(() => {
  const form = document.getElementById("login-form");
  const message = document.getElementById("login-message");
  const params = new URLSearchParams(location.search);

  function nextPath() {
    // Only a page of this site. Browsers drop tabs and newlines from a URL and read "\" as
    // "/", so "/<TAB>/host" would become "//host": refuse those characters, resolve the
    // target as the browser will, and go to the absolute URL only if it stays here ("/.//host"
    // resolves to the path "//host", which as a relative link would name another host).
    const target = params.get("next") || "/";
    if (!target.startsWith("/") || /[\u0000-\u0020\u007f\\]/.test(target)) return "/";
    try {
      const resolved = new URL(target, location.origin);
      return resolved.origin === location.origin ? resolved.href : "/";
    } catch (error) {
      return "/";
    }
  }

  async function logIn(body) {
    const response = await fetch("/api/login", {
      method: "POST",
      credentials: "same-origin",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    });
    const data = await response.json().catch(() => ({}));
    if (!response.ok) throw new Error(data.error || `refused (${response.status})`);
    sessionStorage.setItem("cblrs-session", data.session);
    window.cblrsLoggedIn = { user: data.user, role: data.role };
    location.assign(nextPath());
  }

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    message.textContent = "";
    const button = document.getElementById("login-button");
    button.disabled = true;
    try {
      await logIn({
        user: document.getElementById("user-name").value,
        password: document.getElementById("password").value,
      });
    } catch (error) {
      message.textContent = error.message;
      document.getElementById("password").value = "";
    } finally {
      button.disabled = false;
    }
  });

  // The run's login link (/login?token=...): log in with its token, out of the address bar
  // (and the history) first.
  if (params.has("token")) {
    const token = params.get("token");
    params.delete("token");
    history.replaceState(null, "", `/login${params.toString() ? `?${params}` : ""}`);
    logIn({ token }).catch(() => {
      message.textContent = "This login link is not valid: it changes each time the dashboard "
        + "starts. Open the link it printed last.";
    });
  }
})();
