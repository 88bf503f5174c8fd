// Shared by the pages, loaded before their own script. A token comes in the address's fragment
// (/#token=...), which browsers never send: it becomes the dojo_token cookie every later request
// of the page carries (the server takes no token in a URL), and leaves the address bar.
"use strict";
(() => {
  const token = new URLSearchParams(location.hash.slice(1)).get("token");
  if (!token) return;
  const secure = location.protocol === "https:" ? "; Secure" : "";
  document.cookie = `dojo_token=${encodeURIComponent(token)}; path=/; SameSite=Strict${secure}`;
  history.replaceState(null, "", location.pathname + location.search);
})();
