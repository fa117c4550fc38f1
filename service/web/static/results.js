/* The results page: a sort picked by clicking a column head is kept by the filter
 * form (its hidden "sort" field follows the grid's data-sort after each swap). */
document.addEventListener("htmx:afterSwap", (event) => {
  const grid = document.getElementById("results-grid");
  const sort = document.getElementById("results-sort");
  if (grid && sort && event.detail.target.id === "results-grid") sort.value = grid.dataset.sort || "";
});
