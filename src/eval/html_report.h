// A self-contained HTML report: one file with tables, charts (inline SVG) and videos (mp4
// embedded as data URIs), so it opens in any browser with nothing beside it.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

namespace dojo::eval {

struct Series {
  std::string name;
  std::vector<double> x, y;
};

// Columns `x_column` and `y_column` of a CSV with a header row (empty cells skipped).
// Throws dojo::Error naming the file when it or a column is missing.
Series read_csv_series(const std::filesystem::path& csv, const std::string& x_column,
                       const std::string& y_column, const std::string& name);

class HtmlReport {
 public:
  explicit HtmlReport(std::string title);
  void heading(const std::string& text);
  void paragraph(const std::string& text);  // escaped
  void table(const std::vector<std::string>& header, const std::vector<std::vector<std::string>>& rows);
  // Embeds the mp4 (H.264 plays in every browser).
  void video(const std::filesystem::path& mp4, const std::string& caption);
  // Line chart of the series (moving average over `smooth` points when > 1), log y when asked.
  void line_chart(const std::string& title, const std::vector<Series>& series, const std::string& x_label,
                  const std::string& y_label, bool log_y = false, int smooth = 1);
  // Points (x, y) in [0, 1] x [0, 1], each labelled, with the diagonal y = x drawn: where two
  // measurements of the same quantity agree (per-policy success rates in two worlds).
  void unit_scatter(const std::string& title, const std::vector<std::string>& labels,
                    const std::vector<double>& x, const std::vector<double>& y, const std::string& x_label,
                    const std::string& y_label);
  std::string html() const;
  void write(const std::filesystem::path& path) const;  // atomically

 private:
  std::string title_;
  std::string body_;
};

std::string html_escape(const std::string& text);
std::string base64_encode(const std::string& bytes);

}  // namespace dojo::eval
