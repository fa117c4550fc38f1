/* The share page after a link was made: its token is in the page's fragment
 * (#new=<token>, never sent to the server); the address is shown with a copy button,
 * then the fragment and ?created= leave the URL, so a reload shows the plain page
 * (and posts nothing: the form was answered by a redirect). The box's data-state
 * says which it showed: "shown" or "gone". */
(function () {
  "use strict";
  const box = document.getElementById("share-created");
  if (!box) return;
  const m = /^#new=([A-Za-z0-9_-]+)$/.exec(location.hash);
  const input = document.getElementById("new-share-url");
  if (m) {
    input.value = `${location.origin}/s/${m[1]}`;
    input.focus();
    input.select();
    box.dataset.state = "shown";
  } else {
    input.closest(".copy-row").hidden = true;
    document.getElementById("share-gone").hidden = false;
    box.dataset.state = "gone";
  }
  history.replaceState(null, "", location.pathname);
})();
